"""``garmentnerf`` command line: one entry point, one module per subcommand group.

Every user-facing failure (bad file, bad name, impossible setting) ends as one line on stderr
and exit code 2; ``--debug`` shows the traceback instead.
"""

from __future__ import annotations

import argparse
import errno
import faulthandler
import os
import signal
import sys

import garmentnerf.startup  # noqa: F401 - before the subcommands: its clock is the command's start
from garmentnerf.cli import (bake_cmd, bench_cmd, body_cmd, data_cmd, demo_cmd, eval_cmd, maps_cmd, motion_cmd, render_cmd,
                             train_cmd, view_cmd)
from garmentnerf.cli import export_cmd
from garmentnerf.interrupts import interrupting


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="garmentnerf",
        description="Garment Animation NeRF: bodies, motions, info maps, training and previewing.",
    )
    parser.add_argument("--debug", action="store_true", help="show full tracebacks on errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    body_cmd.register(sub)
    motion_cmd.register(sub)
    maps_cmd.register(sub)
    data_cmd.register(sub)
    bench_cmd.register(sub)
    view_cmd.register(sub)
    render_cmd.register(sub)
    train_cmd.register(sub)
    eval_cmd.register(sub)  # eval and report
    demo_cmd.register(sub)
    bake_cmd.register(sub)
    export_cmd.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("garmentnerf: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # output piped into e.g. `head`, which stopped reading
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except Exception as exc:  # noqa: BLE001 - the one place that turns errors into messages
        if args.debug or not _is_user_error(exc):
            raise
        print(f"garmentnerf: error: {exc}", file=sys.stderr)
        return 2


def _is_user_error(exc: BaseException) -> bool:
    """Errors that describe bad input rather than a bug in garmentnerf."""
    from garmentnerf.gl.context import GLUnavailableError  # lazy: keeps moderngl out of 'garmentnerf --help'

    if isinstance(exc, OSError) and exc.errno in _USER_ERRNOS:
        return True
    simulate = sys.modules.get("garmentnerf.data.simulate")  # loaded whenever one can have been raised
    if simulate is not None and isinstance(exc, simulate.SimulationError):
        return True  # the cloth diverged with the given settings: say so, with the settings to change
    return isinstance(exc, (ValueError, FileNotFoundError, FileExistsError, IsADirectoryError, NotADirectoryError,
                            PermissionError, GLUnavailableError))


#: Operating-system errors that are the machine's state, not a bug: a full disk or quota, a
#: read-only file system, no permission, a name that is too long or runs through a file.
_USER_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM,
                          errno.ENAMETOOLONG, errno.ENOTDIR, errno.EISDIR})


def run() -> None:
    """The ``garmentnerf`` executable: :func:`main`, with Python's fault handler on, so that a crash
    in native code (the GL driver, torch) prints the Python stack it happened under to stderr, and
    with Ctrl-C raising :class:`~garmentnerf.interrupts.Interrupted` (so that a command stopped by
    it exits with status 130, whatever code the interrupt landed in)."""
    faulthandler.enable()
    with interrupting(signal.SIGINT):
        status = main()
    sys.exit(status)


if __name__ == "__main__":
    run()
