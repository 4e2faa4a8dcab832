"""The bounds of the arguments that scale what a command allocates or how long it runs.

Every such argument has a documented :class:`Bound` here, and each command checks its arguments
against them right after reading them, before loading a model or allocating anything large
(this module imports nothing heavy, so a refusal comes within a second). A value outside is
refused in one line naming the flag, the bound and why it is there.

=====================  ==========================================  ========================================
bound                  arguments                                   why
=====================  ==========================================  ========================================
:data:`QUALITY`        ``render --quality``, ``eval --quality``    rays grow with its square
:data:`VIDEO_FPS`      ``render --fps``, a camera path's ``fps``    ffmpeg writes nothing outside it
:data:`MOTION_FPS`     ``--fps`` of a motion (``maps``, ``body      resampled frames grow with it
                       export``, ``render``'s motion ...)
:data:`HISTORY`        ``maps --history``, ``report --variants     info-map channels grow with it
                       kN``
:data:`PLAYBACK`       ``bench --playback-frames``                 the benchmark's time grows with it
=====================  ==========================================  ========================================

Frame ranges are bounded by :data:`garmentnerf.ranges.MAX_FRAME`, render sizes by ``render --size``'s
8..8192 and the per-frame caches of training by ``train --cache-gib``.

Memory
    Within those bounds a render can still outgrow the machine (``render --size 8192`` holds 67 million
    output pixels; ``--quality 4`` renders 16 times a training view's pixels), so ``render`` and ``eval``
    also compare an estimate of their peak memory (:func:`render_memory`: the process's base, plus
    rays x :data:`BYTES_PER_RAY`, rendered pixels x :data:`BYTES_PER_RENDERED_PIXEL` and output pixels x
    :data:`BYTES_PER_OUTPUT_PIXEL`, costs measured on the bundled demos and rounded up) with what this
    process may still allocate (:func:`available_memory`: the machine's free memory, an address-space
    limit, a control group's limit; the least of them) and refuse one that does not fit in one line
    naming the arguments and both figures (:func:`check_memory`). ``--max-memory-gib N`` replaces that
    figure for a user who knows better (swap, or a limit of their own: :data:`MEMORY_GIB`).

    The check is made twice: before torch loads, with what does not depend on the render preset (the
    output pixels: refused within a second), and once the preset is known, before the model loads.
    The history slots of ``report``'s ``kN`` variants need no estimate: they add 3 channels of the info
    maps per slot, whose per-frame cache training bounds by ``train --cache-gib``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["Bound", "QUALITY", "VIDEO_FPS", "MOTION_FPS", "HISTORY", "PLAYBACK", "MEMORY_GIB", "BASE_BYTES",
           "BYTES_PER_RAY", "BYTES_PER_RENDERED_PIXEL", "BYTES_PER_OUTPUT_PIXEL", "RenderGeometry", "RenderMemory",
           "render_memory", "available_memory", "check_memory"]


@dataclass(frozen=True)
class Bound:
    """The values an argument may take: ``low .. high`` (whole numbers only with ``whole``), and why."""

    low: float
    high: float
    why: str
    whole: bool = False

    def check(self, value, flag: str):
        """``value`` (a float, or an int when ``whole``) when it is within the bound; ValueError of one
        line naming ``flag``, the bound and why otherwise (NaN and non-numbers included)."""
        try:
            number = float(value)
        except (TypeError, ValueError, OverflowError):
            raise ValueError(f"{flag} must be a number, got {value!r}") from None
        if self.whole and not (math.isfinite(number) and number == int(number)):
            raise ValueError(f"{flag} must be a whole number, got {value!r}")
        if not (self.low <= number <= self.high):  # also NaN
            shown = f"{value:g}" if isinstance(value, (int, float)) else repr(value)
            raise ValueError(f"{flag} must be in {self.low:g}..{self.high:g} ({self.why}), got {shown}")
        return int(number) if self.whole else number


#: Render quality, as a fraction of the pixel density the model was trained at.
QUALITY = Bound(1.0 / 16.0, 4.0, "fractions of the trained pixel density: below, no character is left in "
                                 "the view; above, the rays, which grow with its square, outgrow memory")
#: Frames per second of a video.
VIDEO_FPS = Bound(0.1, 1000.0, "frames per second: ffmpeg writes an empty file below, no player shows more")
#: Frames per second a motion may be resampled to.
MOTION_FPS = Bound(1.0, 1000.0, "frames per second: the resampled motion's frames, and memory, grow with it")
#: Velocity history slots of the info maps.
HISTORY = Bound(0, 8, "velocity history slots: the info maps' channels grow with them", whole=True)
#: Frames played per preset by the playback benchmark.
PLAYBACK = Bound(1, 240, "frames played per preset: the benchmark's time grows with them", whole=True)
#: What ``--max-memory-gib`` may say: the memory a command may use instead of what the machine has free.
MEMORY_GIB = Bound(0.25, 65536, "GiB a render or evaluation may use instead of the memory the machine has free")


# ---- peak memory of a render ---------------------------------------------------------------------------
#: Resident memory of a render or evaluation before its first ray: the interpreter, torch, the model, the
#: GL context and the metrics' networks (measured with the bundled demos: 0.66 GiB for render, 0.87 GiB
#: for eval).
BASE_BYTES = int(0.9 * 2**30)
#: Memory per ray while it is rendered: its samples' positions, features and outputs (measured: 3.7 to
#: 4.6 KiB at 4 thousand to 262 thousand rays; the larger renders cost less per ray).
BYTES_PER_RAY = 4096
#: Memory per pixel of the rendered maps (weights, coverage, radiance, depth, before resampling; measured
#: about 110 B).
BYTES_PER_RENDERED_PIXEL = 128
#: Memory per output pixel: the maps resampled to it, the composite and the 8-bit image (measured: 164 to
#: 179 B at 4 to 17 million pixels).
BYTES_PER_OUTPUT_PIXEL = 192


@dataclass(frozen=True)
class RenderGeometry:
    """What a run's render size depends on, read from the run and its scene.

    Attributes:
        trained_side: the longer side, in pixels, of a training view at the density the model was trained
            at (``quality = 1``).
        upsample: rendered pixels per ray along a side (the decoder's upsampling).
        image_size: (width, height) of the scene's cameras.
    """

    trained_side: float
    upsample: int
    image_size: tuple[int, int]


@dataclass(frozen=True)
class RenderMemory:
    """An estimate of a render's peak memory (:func:`render_memory`): its parts and their sum."""

    rays: int
    rendered_pixels: int
    output_pixels: int
    base: int = BASE_BYTES

    @property
    def peak_bytes(self) -> int:
        return (self.base + self.rays * BYTES_PER_RAY + self.rendered_pixels * BYTES_PER_RENDERED_PIXEL
                + self.output_pixels * BYTES_PER_OUTPUT_PIXEL)

    def parts(self) -> str:
        """The counts it was made from, for a message."""
        def millions(n: int) -> str:
            return f"{n / 1e6:.3g} million"

        counted = [f"{millions(self.output_pixels)} output pixels"]
        if self.rendered_pixels:
            counted += [f"{millions(self.rendered_pixels)} rendered", f"{millions(self.rays)} rays"]
        return ", ".join(counted)


def render_memory(geometry: RenderGeometry, width: int, height: int, quality: float | None = None) -> RenderMemory:
    """The estimated peak of rendering a ``width x height`` image of a run (``geometry``) at ``quality``.

    The rendered pixels follow ``RenderSession``'s resolution rule: the frame at ``quality`` times the
    trained density, ``quality**2 * trained_side**2`` over the frame's aspect. A preset that renders the
    character's rectangle renders the character at that density too, so about as many pixels (more only
    for a view nearer the character than the training cameras, at most one per output pixel), and the
    rays of the rectangle alone: the frame's rays, ``rendered / upsample**2``, bound them. With ``quality``
    None (not known yet: before the preset is read) only what any render needs is counted: the output
    pixels.
    """
    width, height = int(width), int(height)
    output = width * height
    if quality is None:
        return RenderMemory(0, 0, output)
    rendered = (float(quality) * geometry.trained_side) ** 2 * output / max(width, height) ** 2
    return RenderMemory(math.ceil(rendered / geometry.upsample**2), math.ceil(rendered), output)


def _meminfo_available() -> int | None:
    try:
        import psutil  # optional: the same figure, on more systems
    except ImportError:
        pass
    else:
        return int(psutil.virtual_memory().available)
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def _read_number(path: str) -> int | None:
    try:
        with open(path, encoding="ascii") as fh:
            text = fh.read().strip()
    except OSError:
        return None
    return int(text) if text.isdigit() else None  # "max": no limit


def _address_space_left() -> int | None:
    try:
        import resource
    except ImportError:  # pragma: no cover - not POSIX
        return None
    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    if soft == resource.RLIM_INFINITY or soft < 0:
        return None
    used = 0
    try:
        with open("/proc/self/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("VmSize:"):
                    used = int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return max(0, soft - used)


def available_memory() -> tuple[int, str] | None:
    """(bytes this process may still allocate, where that figure comes from), the least of: the memory
    the machine has available (``psutil`` when installed, else ``/proc/meminfo``'s MemAvailable), what
    this process's address-space limit (``ulimit -v``, ``prlimit --as``) leaves, and what its control
    group's ``memory.max`` leaves. None where none of them can be read."""
    found = []
    free = _meminfo_available()
    if free is not None:
        found.append((free, "the machine has available"))
    left = _address_space_left()
    if left is not None:
        found.append((left, "this process's address-space limit leaves"))
    limit, current = _read_number("/sys/fs/cgroup/memory.max"), _read_number("/sys/fs/cgroup/memory.current")
    if limit is not None and current is not None:
        found.append((max(0, limit - current), "its control group's memory limit leaves"))
    return min(found) if found else None


def check_memory(estimate: RenderMemory, what: str, max_gib: float | None = None,
                 lower: str = "them") -> None:
    """Refuse ``estimate`` (of ``what``, e.g. ``render --size 8192``) when its peak is more than
    ``max_gib`` GiB (``--max-memory-gib``), or without it more than :func:`available_memory`: ValueError
    of one line with both figures, what the estimate counted and what to change (``lower``)."""
    need = estimate.peak_bytes
    if max_gib is not None:
        budget, source = float(max_gib) * 2**30, "--max-memory-gib allows"
    else:
        found = available_memory()
        if found is None:
            return
        budget, source = found
    if need > budget:
        flag = "" if max_gib is not None else ", or pass --max-memory-gib N to allow N GiB"
        raise ValueError(f"{what} needs about {need / 2**30:.1f} GiB at its peak (estimated: {estimate.parts()}), "
                         f"more than the {budget / 2**30:.1f} GiB {source}; lower {lower}{flag}")

