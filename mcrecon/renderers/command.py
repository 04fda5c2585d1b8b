"""Out-of-process renderers: exchange HDF5 files with a command.

Protocol version 1 (specified in ``docs/renderer-protocol.md``): for each
round mcrecon writes a *request* file, starts the renderer command (an
argument list, never through a shell) with the ``{request}`` and
``{reply}`` placeholders replaced by the two paths, waits for it to exit
(with a time-out), and reads the *reply*, a file in the sample-log
format: positions, values and any per-sample features (``/features/NAME``,
shape ``(N,)`` or ``(N, k)``, integer or float; the same names and shapes
every round; NaN/Inf set to 0 and warned), which reach the run's log and
the statistics of methods that read features.  Every failure
(cannot start, time-out, non-zero exit, missing, malformed or short reply,
a bad feature) raises :class:`~mcrecon.errors.RendererError`; the driver
has committed every earlier round, so the run stays resumable.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Sequence

import h5py
import numpy as np

from ..errors import InputError, RendererError
from ..io._atomic import atomic_path
from ..core.requests import SampleBatch, SampleRequest, check_sampler
from .spec_format import command_spec

__all__ = ["CommandRenderer", "write_request", "write_reply", "read_request", "request_channels", "REQUEST_FORMAT",
           "remove_stale_workdirs"]

WORKDIR_PREFIX = "mcrecon-renderer-"


def _pid_alive(pid: int) -> bool:
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # alive, owned by another user
        return True
    except OSError:
        return False
    return True


def remove_stale_workdirs(tmpdir=None) -> list[Path]:
    """Remove ``mcrecon-renderer-PID-*`` directories whose owner process has died.

    A run killed with SIGKILL cannot remove its private work directory; the
    next :class:`CommandRenderer` does.  Directories of live processes, of
    other users and without a PID in their name (older versions) are left
    alone.  Returns the directories removed.
    """
    root = Path(tmpdir if tmpdir is not None else tempfile.gettempdir())
    removed = []
    try:
        entries = list(root.glob(WORKDIR_PREFIX + "*"))
    except OSError:
        return removed
    for d in entries:
        m = re.fullmatch(re.escape(WORKDIR_PREFIX) + r"(\d+)-.+", d.name)
        if not m or _pid_alive(int(m.group(1))):
            continue
        try:
            if d.is_symlink() or not d.is_dir() or d.stat().st_uid != os.getuid():
                continue
        except OSError:
            continue
        shutil.rmtree(d, ignore_errors=True)
        if not d.exists():
            removed.append(d)
    return removed

REQUEST_FORMAT = "mcrecon-request"
REQUEST_VERSION = 1


def write_request(path, request: SampleRequest, *, channels: Sequence[str]) -> Path:
    """Write a request file atomically (temporary file, then rename)."""
    path = Path(path)
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as f:
            # Types as docs/renderer-protocol.md lists them: strings variable-length UTF-8,
            # integers int64 except the seed (uint64).
            f.attrs["format"] = REQUEST_FORMAT
            f.attrs["format_version"] = np.int64(REQUEST_VERSION)
            f.attrs["width"] = np.int64(request.width)
            f.attrs["height"] = np.int64(request.height)
            f.attrs["channels"] = np.array(list(channels), dtype=h5py.string_dtype())
            f.attrs["round"] = np.int64(request.round_index)
            f.attrs["seed"] = np.uint64(request.seed)
            f.attrs["n_total"] = np.int64(request.total)
            if request.counts is not None:
                f.create_dataset("counts", data=request.counts.astype(np.int64))
            if request.positions is not None:
                f.create_dataset("positions", data=request.positions.astype(np.float64))
            if request.first_index is not None:
                f.create_dataset("first_index", data=request.first_index.astype(np.int64))
    return path


def _text(v):
    """A string attribute's value as str: variable-length UTF-8 (str) or fixed-length ASCII (bytes)."""
    if isinstance(v, np.ndarray) and v.shape == () or isinstance(v, np.generic):
        v = v.item()
    return v.decode("utf-8") if isinstance(v, bytes) else v


def write_reply(path, positions, values, *, width: int, height: int, channels: Sequence[str],
                sampler: str | None = None, features=None) -> Path:
    """A reply file (a sample log, :func:`mcrecon.io.write_log`) for a Python renderer, declaring its
    ``sampler`` (root attribute; None: none, which reads as ``independent``; docs/renderer-protocol.md)."""
    from ..io import write_log

    path = write_log(path, positions, values, width=width, height=height, channels=channels, features=features)
    if sampler is not None:
        with h5py.File(path, "a") as f:
            f.attrs["sampler"] = check_sampler(sampler, where=str(path))
    return Path(path)


def request_channels(path) -> tuple[str, ...]:
    """The channel names of a request file (either string type), for a renderer that needs them."""
    with h5py.File(path, "r") as f:
        return tuple(_text(x) for x in np.atleast_1d(f.attrs["channels"]).tolist())


def read_request(path) -> SampleRequest:
    """Read a request file (what a Python renderer does first).

    Any problem (not HDF5, another format, a missing or malformed attribute
    or dataset, counts, positions or first_index that do not fit the film, ``n_total``
    other than ``sum(counts) + M``) raises a one-line
    :class:`~mcrecon.errors.InputError` naming the file.  Strings may be
    variable-length UTF-8 or fixed-length ASCII, integers of any integer
    type (docs/renderer-protocol.md).
    """
    path = Path(path)

    def one_line(exc) -> str:
        return " ".join(str(exc).split()) or type(exc).__name__

    try:
        f = h5py.File(path, "r")
    except (OSError, ValueError, RuntimeError) as exc:
        raise InputError(str(path), "file", f"not a readable request file: {one_line(exc)}") from None
    with f:
        try:
            if _text(f.attrs.get("format")) != REQUEST_FORMAT:
                raise InputError(str(path), "attribute format", f"expected {REQUEST_FORMAT!r}")
            ch = f.attrs.get("channels")
            if ch is not None:
                names = [_text(x) for x in np.atleast_1d(ch).tolist()]
                if not names or not all(isinstance(x, str) and x for x in names):
                    raise InputError(str(path), "attribute channels", f"got {one_line(repr(ch))[:60]}, expected "
                                     "an array of non-empty strings")
            ints = {}
            for key in ("width", "height", "round", "seed"):
                v = f.attrs.get(key)
                v = v.item() if isinstance(v, np.ndarray) and v.size == 1 else v
                if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)):
                    got = (f"an array of shape {v.shape} dtype {v.dtype}" if isinstance(v, np.ndarray)
                           else one_line(repr(v))[:60])
                    raise InputError(str(path), f"attribute {key}", f"got {got}, expected an integer")
                ints[key] = int(v)
            if ints["width"] < 1 or ints["height"] < 1 or ints["round"] < 0 or ints["seed"] < 0:
                raise InputError(str(path), "attributes width/height/round/seed",
                                 f"got {ints}, expected width, height >= 1 and round, seed >= 0")
            arrays = {}
            film = (ints["height"], ints["width"])
            for key, shape in (("counts", film), ("positions", None), ("first_index", film)):
                d = f.get(key)
                if d is None:
                    arrays[key] = None
                    continue
                ok = isinstance(d, h5py.Dataset) and d.dtype.kind in ("iuf" if key == "positions" else "iu")
                ok = ok and (d.shape == shape if shape else (d.ndim == 2 and d.shape[1] == 2))
                if not ok:
                    expect = f"{shape} integers" if shape else "(M, 2) numbers"
                    raise InputError(str(path), f"dataset /{key}",
                                     f"shape {getattr(d, 'shape', None)} dtype {getattr(d, 'dtype', None)}, "
                                     f"expected {expect}")
                arrays[key] = d[...]
            first = arrays["first_index"]
            if first is not None and first.size and (first.dtype.kind == "u" and first.max() > np.iinfo(np.int64).max
                                                     or first.dtype.kind == "i" and first.min() < 0):
                raise InputError(str(path), "dataset /first_index", "expected sample indices >= 0 (int64)")
            req = SampleRequest(ints["width"], ints["height"], counts=arrays["counts"],
                                positions=arrays["positions"], round_index=ints["round"], seed=ints["seed"],
                                first_index=None if first is None else first.astype(np.int64))
            total = f.attrs.get("n_total")
            total = total.item() if isinstance(total, np.ndarray) and total.size == 1 else total
            if total is not None and (isinstance(total, (bool, np.bool_)) or not isinstance(total, (int, np.integer))
                                      or int(total) != req.total):
                got = int(total) if isinstance(total, (int, np.integer)) else one_line(repr(total))[:60]
                raise InputError(str(path), "attribute n_total", f"got {got}, expected "
                                 f"sum(counts) + M = {req.total}, the number of samples the reply must hold")
            return req
        except InputError:
            raise
        except (OSError, ValueError, TypeError, KeyError, RuntimeError, OverflowError) as exc:
            raise InputError(str(path), "file", f"malformed request: {one_line(exc)}") from None


class CommandRenderer:
    """A renderer that is an external command speaking the file protocol.

    Parameters
    ----------
    argv : sequence of str
        The command; the items ``{request}`` and ``{reply}`` (also inside
        an item, e.g. ``--out={reply}``) are replaced by the file paths.
        It is run directly (no shell).
    width, height : int
    channels : sequence of str
    timeout : float, optional
        Seconds per round; the command is killed after it.
    workdir : path-like, optional
        Where request/reply files go (default: a private temporary
        directory ``mcrecon-renderer-PID-XXXX``, removed when the renderer
        is collected; those left by killed processes are removed by the
        next CommandRenderer).  They are removed after each successful round.
    cwd : path-like, optional
        The directory the command runs in (default: the current one).

    Attributes
    ----------
    sampler : str or None
        What the command's samples of a pixel are, as its last reply file declared it (root attribute
        ``sampler``: ``independent``, the default when absent, or ``sobol``; docs/renderer-protocol.md);
        None before the first reply.
    """

    #: Every reply's arrays are new (never a buffer the renderer fills again): the driver keeps them
    #: for the log while the next round renders, without a copy (renderers without it are copied).
    fresh_replies = True

    def __init__(self, argv: Sequence[str], *, width: int, height: int,
                 channels: Sequence[str] = ("R", "G", "B"), timeout: float | None = 600.0, workdir=None,
                 cwd=None):
        argv = [str(a) for a in argv]
        if not argv:
            raise InputError("renderer command", "argv", "empty")
        joined = " ".join(argv)
        if "{request}" not in joined or "{reply}" not in joined:
            raise InputError("renderer command", "argv",
                             f"{joined!r} lacks the {{request}} and {{reply}} placeholders")
        if timeout is not None and not timeout > 0:
            raise InputError("renderer command", "timeout", f"got {timeout}, expected seconds > 0")
        self.argv = argv
        self.width, self.height = int(width), int(height)
        self.channels = tuple(channels)
        self.timeout = timeout
        self._own_workdir = workdir is None
        if workdir is None:
            remove_stale_workdirs()
            workdir = tempfile.mkdtemp(prefix=f"{WORKDIR_PREFIX}{os.getpid()}-")
        self.workdir = Path(workdir).absolute()   # the command may run elsewhere (cwd)
        self.cwd = None if cwd is None else str(cwd)
        self.workdir.mkdir(parents=True, exist_ok=True)
        self.name = f"renderer command {Path(argv[0]).name}"
        self.last_render_seconds = None
        # {name: per-sample shape} of the first reply: every later reply must send the same
        self._feature_layout: dict[str, tuple[int, ...]] | None = None
        self._warned_zeroed = False
        self.sampler: str | None = None

    def spec(self) -> dict:
        """How to build this renderer again (:func:`mcrecon.renderers.spec_format.command_spec`): a work
        directory of its own is not recorded (a resumed run makes a new one)."""
        return command_spec(self.argv, width=self.width, height=self.height, channels=self.channels,
                            timeout=self.timeout, workdir=None if self._own_workdir else self.workdir, cwd=self.cwd)

    def __del__(self):
        if getattr(self, "_own_workdir", False):
            shutil.rmtree(getattr(self, "workdir", ""), ignore_errors=True)

    def render(self, request: SampleRequest) -> SampleBatch:
        from ..io.reader import read_log

        stem = f"round-{request.round_index:05d}"
        req_path = self.workdir / f"{stem}.request.h5"
        reply_path = self.workdir / f"{stem}.reply.h5"
        for p in (req_path, reply_path):
            if p.exists():
                p.unlink()
        write_request(req_path, request, channels=self.channels)
        argv = [a.replace("{request}", str(req_path)).replace("{reply}", str(reply_path)) for a in self.argv]
        t0 = time.perf_counter()
        try:
            proc = subprocess.run(argv, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                  timeout=self.timeout, shell=False, check=False, cwd=self.cwd)
        except FileNotFoundError:
            raise RendererError(self.name, "command", f"{argv[0]!r} not found") from None
        except PermissionError:
            raise RendererError(self.name, "command", f"{argv[0]!r} is not executable") from None
        except subprocess.TimeoutExpired:
            raise RendererError(self.name, "time-out", f"round {request.round_index} took longer than "
                                f"{self.timeout} s; the command was killed (raise --timeout, or resume)") from None
        self.last_render_seconds = time.perf_counter() - t0
        if proc.returncode != 0:
            tail = proc.stderr.decode(errors="replace").strip().splitlines()
            tail = tail[-1] if tail else "(no stderr)"
            raise RendererError(self.name, "exit status", f"{proc.returncode} in round {request.round_index}: {tail}")
        if not reply_path.exists():
            raise RendererError(self.name, "reply", f"{reply_path} was not written")
        self._check_declared_length(reply_path, request)
        try:
            reply = read_log(reply_path)
            data = reply.read_all()
        except InputError as exc:
            if exc.field == "attribute sampler":  # the renderer's declaration, refused as it names it
                raise
            if exc.field.startswith("dataset /features/"):
                raise RendererError(self.name, f"reply {reply_path} {exc.field}", exc.problem) from None
            raise RendererError(self.name, "reply", f"malformed: {exc}") from None
        if (reply.width, reply.height) != (self.width, self.height):
            raise RendererError(self.name, "reply width/height", f"{reply.width}x{reply.height}, "
                                f"expected {self.width}x{self.height}")
        if tuple(reply.channels) != self.channels:
            raise RendererError(self.name, "reply channels", f"{','.join(reply.channels)}, "
                                f"expected {','.join(self.channels)}")
        features = self._read_features(reply, reply_path, request.round_index)
        with h5py.File(reply_path, "r") as f:  # the renderer's declaration, absent: independent samples
            self.sampler = check_sampler(f.attrs.get("sampler"), where=str(reply_path), field="attribute sampler")
        for p in (req_path, reply_path):
            p.unlink(missing_ok=True)
        return SampleBatch(np.asarray(data.positions, np.float64), data.values, features)

    def _check_declared_length(self, reply_path: Path, request: SampleRequest) -> None:
        """Refuse a reply whose datasets declare another number of samples than requested, from the
        file's metadata alone: a reply declaring 200 M rows (unwritten chunks cost no disk) would
        otherwise be read whole before its length is checked."""
        from ..io.logformat import declared_samples

        try:
            n = declared_samples(reply_path)
        except InputError as exc:
            raise RendererError(self.name, "reply", f"malformed: {exc}") from None
        if n != request.total:
            raise RendererError(self.name, "reply length", f"{reply_path} declares {n} samples, requested "
                                f"{request.total} (round {request.round_index})")

    def _read_features(self, reply, reply_path: Path, round_index: int) -> dict[str, np.ndarray]:
        """The reply's per-sample features ``/features/NAME``, validated at the boundary.

        Each is (N,) or (N, k) of a numeric dtype (integers, floats, bool
        as 0/1; not strings); the names and per-sample shapes are those of
        the first reply (the first reply decides, as in the log); values
        that are not finite or beyond the features' limit (a DBL_MAX "no
        hit") are set to 0 in a copy and warned once per renderer, as
        :func:`mcrecon.core.features.check_features` does (a depth of inf
        where a ray left the scene: the sample's colour is kept).
        ``read_log`` has checked that each is a dataset of at least N rows;
        rows past N are allowed only in a reply that records
        ``n_committed`` (an appended log), as for its positions and values.
        """
        from ..core.features import warn_feature_zeroed, within_feature_limit

        n = reply.n_samples
        features = {}
        if reply.feature_names:
            with h5py.File(reply_path, "r") as f:
                appended = "n_committed" in f.attrs
                for name in reply.feature_names:
                    d = f["features"][name]
                    field = f"reply {reply_path} dataset /features/{name}"
                    if d.ndim == 0 or d.shape[0] < n or (d.shape[0] != n and not appended):
                        raise RendererError(self.name, field, f"shape {d.shape}, expected ({n}, ...): one row per "
                                            "sample")
                    if d.ndim > 2:
                        raise RendererError(self.name, field, f"shape {d.shape}, expected ({n},) or ({n}, k): one "
                                            "row of k components per sample")
                    if d.dtype.kind not in "iufb":
                        raise RendererError(self.name, field, f"dtype {d.dtype}, expected a numeric dtype "
                                            "(integer, float or bool)")
                    # a bool mask is taken as 0/1 (renderer-protocol.md)
                    features[name] = d[:n].astype(np.uint8) if d.dtype.kind == "b" else d[:n]
        layout = {name: tuple(arr.shape[1:]) for name, arr in features.items()}
        if self._feature_layout is None:
            self._feature_layout = layout
        elif layout != self._feature_layout:
            show = lambda lay: ", ".join(f"{k} {(n,) + v}" for k, v in sorted(lay.items())) or "none"  # noqa: E731
            raise RendererError(self.name, f"reply {reply_path} /features",
                                f"round {round_index} sends {show(layout)}; the first reply sent "
                                f"{show(self._feature_layout)}: every round must send "
                                "the same features with the same shapes")
        zeroed = 0
        for name, arr in features.items():
            if arr.dtype.kind == "f":
                finite = within_feature_limit(arr)  # NaN, Inf and "no hit" sentinels (DBL_MAX), warned once
                if not finite.all():
                    rows = ~finite if arr.ndim == 1 else ~finite.all(axis=1)
                    zeroed = max(zeroed, int(rows.sum()))
                    features[name] = np.where(finite, arr, arr.dtype.type(0))
        if zeroed and not self._warned_zeroed:
            self._warned_zeroed = True  # once per renderer: a scene with sky has them every round
            warn_feature_zeroed(f"{self.name}: round {round_index} (later rounds are not warned again)", zeroed,
                                stacklevel=4)
        return features
