"""The previewer's keyboard shortcuts: ONE table that drives key handling and the help window.

Keys are named by their ``imgui.Key`` attribute (``"space"``, ``"comma"``, ``"f1"``, ``"_1"``); imgui's
GLFW backend maps physical keys through the keyboard layout, so ``"f"`` is the key labelled F.
Shortcuts fire only when imgui is not taking text input and no Ctrl/Alt/Super modifier is held.
This module needs no window: :func:`resolve` takes the imgui module when keys are polled.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Shortcut:
    """Keys that trigger one app action.

    Attributes:
        keys: imgui.Key attribute names; any of them triggers the action.
        action: the name of the :class:`~garmentnerf.viewer.app.App` action (see ``App.actions``).
        description: what the help window says.
        repeat: whether holding the key repeats the action (frame stepping does; toggles do not).
    """

    keys: tuple[str, ...]
    action: str
    description: str
    repeat: bool = False


SHORTCUTS: tuple[Shortcut, ...] = (
    Shortcut(("space",), "toggle_play", "play / pause"),
    Shortcut(("comma", "left_arrow"), "step_back", "previous frame", repeat=True),
    Shortcut(("period", "right_arrow"), "step_forward", "next frame", repeat=True),
    Shortcut(("home",), "first_frame", "first frame"),
    Shortcut(("end",), "last_frame", "last frame"),
    Shortcut(("l",), "toggle_loop", "loop on / off"),
    Shortcut(("left_bracket",), "slower", "half playback speed"),
    Shortcut(("right_bracket",), "faster", "double playback speed"),
    Shortcut(("f", "_1"), "camera_front", "camera: front view"),
    Shortcut(("b", "_3"), "camera_back", "camera: back view"),
    Shortcut(("_2",), "camera_left", "camera: the character's left side"),
    Shortcut(("_4",), "camera_right", "camera: the character's right side"),
    Shortcut(("r",), "reset_camera", "camera: reset to the home view"),
    Shortcut(("t",), "toggle_follow", "camera: follow the body on / off"),
    Shortcut(("k",), "add_keyframe", "camera path: add a keyframe (this view at this frame)"),
    Shortcut(("p",), "toggle_path_view", "camera path: view through the path on / off"),
    Shortcut(("g",), "toggle_grid", "floor grid on / off"),
    Shortcut(("s",), "snapshot", "save a snapshot PNG (snapshot resolution; the network at full quality in the neural view)"),
    Shortcut(("v",), "next_view_mode", "next view mode (neural, ground truth, side by side, difference, body, maps)"),
    Shortcut(("tab",), "toggle_ui", "hide / show the panels"),
    Shortcut(("h", "f1"), "toggle_help", "this help"),
    Shortcut(("escape",), "quit", "quit"),
)

#: Mouse gestures, for the help window (handled in the app, not by key).
MOUSE_HELP: tuple[tuple[str, str], ...] = (
    ("left drag", "orbit (turntable)"),
    ("right / middle drag", "pan"),
    ("shift + left drag", "pan"),
    ("wheel", "zoom"),
)

_LABELS = {
    "space": "Space", "comma": ",", "period": ".", "left_arrow": "Left", "right_arrow": "Right",
    "home": "Home", "end": "End", "left_bracket": "[", "right_bracket": "]", "tab": "Tab",
    "escape": "Esc",
}


def key_label(name: str) -> str:
    """How the help window writes a key: ``comma`` -> ``,``, ``f1`` -> ``F1``, ``_2`` -> ``2``."""
    if name in _LABELS:
        return _LABELS[name]
    if name.startswith("_") and name[1:].isdigit():
        return name[1:]
    return name.upper()


def help_rows(shortcuts=SHORTCUTS) -> list[tuple[str, str]]:
    """(keys, description) rows for the help window, in table order."""
    return [(" / ".join(key_label(k) for k in s.keys), s.description) for s in shortcuts]


def actions(shortcuts=SHORTCUTS) -> list[str]:
    """Every action the table names (each once)."""
    return list(dict.fromkeys(s.action for s in shortcuts))


def action_for_key(name: str, shortcuts=SHORTCUTS) -> str | None:
    """The action bound to a key name, or None."""
    for s in shortcuts:
        if name in s.keys:
            return s.action
    return None


def resolve(imgui, shortcuts=SHORTCUTS) -> list[tuple[object, Shortcut]]:
    """(imgui.Key, shortcut) pairs; raises ValueError naming a key imgui does not know."""
    pairs = []
    for s in shortcuts:
        for name in s.keys:
            key = getattr(imgui.Key, name, None)
            if key is None:
                raise ValueError(f"shortcut key '{name}' is not an imgui.Key")
            pairs.append((key, s))
    return pairs


def pressed_actions(imgui, resolved) -> list[str]:
    """Actions whose keys were pressed since the last imgui frame (call between new_frame and render)."""
    io = imgui.get_io()
    if io.want_text_input or io.key_ctrl or io.key_alt or io.key_super:
        return []
    fired = []
    for key, s in resolved:
        if imgui.is_key_pressed(key, s.repeat) and s.action not in fired:
            fired.append(s.action)
    return fired
