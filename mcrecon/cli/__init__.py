"""The ``mcrecon`` command line: it only composes public calls.

Exit status 0 on success; on bad input, 2 with one line on stderr naming
the file, the field and what was expected (no traceback).

The commands live in :mod:`.commands` and :mod:`.experiments`, what they
share in :mod:`._common`; this module builds the parser and runs one.

Start-up stays quick: every command imports what it uses when it runs,
and the method flags (which need every method class) are added only to
the parser of the command being run (``mcrecon --help`` and
``mcrecon info`` load no method).
"""

from __future__ import annotations

import os
import sys
import warnings

from ..errors import InputError, McreconWarning, RendererError
from . import batch, blender, commands, experiments
from ._common import OneLineParser

__all__ = ["main", "run", "build_parser"]

#: Set when a log write failed inside HDF5 (see :func:`run`).
_STATE = {"hdf5_write_failed": False}


def build_parser(command: str | None = None) -> OneLineParser:
    """The ``mcrecon`` parser.

    With ``command`` (the sub-command about to run), only that command's
    parser gets the method flags, whose groups need the method classes;
    the other sub-commands are complete but for them (never parsed).
    Without it, every parser is complete.
    """
    p = OneLineParser(prog="mcrecon", description="Adaptive sampling and reconstruction for Monte Carlo renderers.")
    sub = p.add_subparsers(dest="command", required=True, parser_class=OneLineParser)
    commands.register(sub, command)
    experiments.register(sub, command)
    batch.register(sub, command)
    blender.register(sub, command)
    return p


def _command_of(argv) -> str | None:
    """The sub-command ``argv`` names: its first word not starting with ``-`` (``mcrecon`` itself has
    no option taking a value), or None (``mcrecon --help``, no command)."""
    return next((a for a in argv if not a.startswith("-")), None)


def _to_devnull(stream) -> None:
    """After a closed pipe: send what is left of ``stream`` to devnull, so the flush at exit cannot
    fail again (as the Python docs on SIGPIPE recommend)."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, stream.fileno())
        os.close(devnull)
    except (OSError, ValueError, AttributeError):  # no file (captured): nothing to flush
        pass


class _ReaderMayLeave:
    """A text stream whose reader may go away (``mcrecon demo | head -3``): after a closed pipe what is
    written is dropped and the command goes on.  Its files are its result and the lines it prints only
    report them, so a reader that stopped reading must not stop the command half way (it had left
    8 of a demo's 15 files, an adaptive run without its rounds JSON, and exit status 0)."""

    def __init__(self, stream):
        self._stream = stream
        self._gone = False

    def write(self, text):
        if not self._gone:
            try:
                return self._stream.write(text)
            except BrokenPipeError:
                self._leave()
        return len(text)

    def flush(self):
        if not self._gone:
            try:
                self._stream.flush()
            except BrokenPipeError:
                self._leave()

    def _leave(self):
        self._gone = True
        _to_devnull(self._stream)

    def __getattr__(self, name):
        return getattr(self._stream, name)


class _Nowhere:
    """The stream of a closed descriptor: takes everything, keeps nothing, is no terminal."""

    def write(self, text):
        return len(text)

    def flush(self):
        pass

    def isatty(self):
        return False


def _how_to_continue(args) -> str:
    """After Ctrl-C: for an adaptive run with a log on disk, the command that continues it (every committed
    round is kept; a log without one holds the run's settings, and the command starts the run), else nothing."""
    import shlex
    from pathlib import Path

    log = getattr(args, "resume", None) or getattr(args, "log", None)
    if getattr(args, "command", None) != "adapt" or not log or not Path(log).is_file():
        return ""
    try:
        from ..io import read_log

        rounds = read_log(log).n_rounds
    except Exception:  # noqa: BLE001 -- a log that cannot be read: no command to offer
        return ""
    out = getattr(args, "output", None)
    resume = f"mcrecon adapt --resume {shlex.quote(str(log))}" + (f" -o {shlex.quote(str(out))}" if out else "")
    if rounds == 0:
        return f" before any round was committed; `{resume}` starts the run from its first round"
    return f"; `{resume}` continues the run from its last committed round"


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else [str(a) for a in argv]
    parser = build_parser(_command_of(argv) or "")  # "": no command, no method flags
    args = parser.parse_args(argv)
    with warnings.catch_warnings():
        warnings.simplefilter("always", McreconWarning)
        showwarning = warnings.showwarning

        def _one_line(message, category, filename, lineno, file=None, line=None):
            if issubclass(category, McreconWarning):
                sys.stderr.write(f"mcrecon: warning: {message}\n")
            else:
                showwarning(message, category, filename, lineno, file, line)

        warnings.showwarning = _one_line
        streams = sys.stdout, sys.stderr
        # a closed descriptor (`2>&-`) leaves the stream None: what would go there is dropped
        sys.stdout, sys.stderr = (_Nowhere() if x is None else _ReaderMayLeave(x) for x in streams)
        try:
            code = int(args.func(args) or 0)
            sys.stdout.flush()  # a reader that went away shows here, not at exit
            return code
        except BrokenPipeError:  # a write that bypassed the wrapper (a library's own handle)
            _to_devnull(streams[0])
            return 0
        except (InputError, RendererError) as exc:
            sys.stderr.write(f"mcrecon: error: {exc}\n")
            if getattr(exc, "write_failed", False):
                _STATE["hdf5_write_failed"] = True  # run() ends the process without HDF5's clean-up
            return 2
        except OSError as exc:  # an output path that cannot be written, a full disk...
            where = exc.filename or "file system"
            sys.stderr.write(f"mcrecon: error: {where}: {exc.strerror or exc}\n")
            return 2
        except KeyboardInterrupt:
            sys.stderr.write(f"mcrecon: interrupted{_how_to_continue(args)}\n")
            return 130
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            sys.stdout, sys.stderr = streams
            warnings.showwarning = showwarning


def run() -> None:
    """The ``mcrecon`` program: :func:`main`, then exit with its status.

    After a log write failed inside HDF5 (a full disk), HDF5 keeps the log
    open because its close cannot flush, and its own clean-up at
    interpreter exit then crashes the process (SIGSEGV, measured with HDF5
    2.0 / h5py 3.x).  Every committed round is on disk already, so the
    process ends with ``os._exit`` after the one-line message instead.
    """
    code = main()
    if _STATE["hdf5_write_failed"]:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    raise SystemExit(code)

