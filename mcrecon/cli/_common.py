"""What every command shares: the one-line parser, method flags, output checks and writing.

Method flags come from the methods' own :class:`~mcrecon.methods.Option`
descriptions: one ``--help`` group per method, and the strings a user
types go to the method unchanged, so :meth:`Option.convert` is the one
place they are validated.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import re
import sys
import textwrap
from pathlib import Path

from ..errors import InputError

__all__ = ["OneLineParser", "HelpFormatter", "parse_size", "finite_float", "add_scene_flags", "add_sampler_flag",
           "method_flags", "add_method_options", "given_method_options", "make_method", "add_exr_read_flags",
           "exr_read_options", "exr_read_flags_given", "check_output", "write_outputs", "jit_notice",
           "compile_notice"]

_DEST = "mopt_"  # argparse dest of a method option: mopt_NAME


class OneLineParser(argparse.ArgumentParser):
    """A parser whose errors are one line on stderr and exit status 2."""

    def error(self, message):
        sys.stderr.write(f"{self.prog}: error: {message}\n")
        raise SystemExit(2)

    def parse_args(self, args=None, namespace=None):
        # argparse's own parse_args, but an unknown long option gets the closest option of the
        # sub-command that was parsing it (`--methd` -> `--method`)
        ns, extras = self.parse_known_args(args, namespace)
        if extras:
            exrs = all(e.lower().endswith(".exr") and not e.startswith("-") for e in extras)
            self.error(f"unrecognized arguments: {' '.join(extras)}{_suggestions(self, ns, extras)}"
                       + (" (several EXRs: quote a seed set's glob, 'shot.seed*.exr', so that the shell leaves "
                          "it to mcrecon)" if exrs else ""))
        return ns


def _leaf_parser(parser, ns):
    """The (sub-)sub-command parser that parsed ``ns`` (the parser itself without sub-commands)."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            child = action.choices.get(getattr(ns, action.dest, None) or "")
            if child is not None:
                return _leaf_parser(child, ns)
    return parser


def _suggestions(parser, ns, extras) -> str:
    """`` (did you mean --x?)`` for the unknown long options of ``extras`` close to an option of the command."""
    import difflib

    known = sorted(o for o in _leaf_parser(parser, ns)._option_string_actions if o.startswith("--"))
    hints = []
    for arg in extras:
        if not arg.startswith("--") or arg == "--":
            continue
        name = arg.split("=", 1)[0]
        close = difflib.get_close_matches(name, known, n=1, cutoff=0.7)
        if close:
            hints.append(f"{name}: did you mean {close[0]}?")
    return f" ({'; '.join(hints)})" if hints else ""


class HelpFormatter(argparse.HelpFormatter):
    """Keeps the line breaks of descriptions (each line wrapped on its own)."""

    def _fill_text(self, text, width, indent):
        return "\n".join(textwrap.fill(line, width, initial_indent=indent, subsequent_indent=indent + "    ")
                         if line.strip() else "" for line in text.splitlines())


def parse_size(text: str, where: str = "--size") -> tuple[int, int]:
    """``WIDTHxHEIGHT`` as ``(width, height)``."""
    try:
        w, h = (int(x) for x in str(text).lower().split("x"))
    except ValueError:
        raise InputError(where, "size", f"{text!r}: expected WIDTHxHEIGHT, e.g. 128x128") from None
    if w < 1 or h < 1:
        raise InputError(where, "size", f"{text!r}: expected at least 1x1")
    from ..io.logformat import MAX_PIXELS

    if w * h > MAX_PIXELS:
        raise InputError(where, "size", f"{text!r}: {w}x{h} = {w * h} pixels, beyond the {MAX_PIXELS} pixels "
                         "mcrecon can hold images of")
    return w, h


def add_scene_flags(parser, *, spp: int = 16, size: str = "128x128", scene: str = "soft_shadow",
                    sampler: bool = False) -> None:
    """The flags of a command that renders a built-in scene: --scene, --spp, --size, --seed (and ``sampler``:
    --sampler, for a command that passes it to the scene renderer)."""
    parser.add_argument("--scene", default=scene, help="built-in scene (see `mcrecon scenes`)")
    parser.add_argument("--spp", type=int, default=spp)
    parser.add_argument("--size", default=size)
    parser.add_argument("--seed", type=int, default=0)
    if sampler:
        add_sampler_flag(parser, default="independent")


#: ``mcrecon.renderers.spec_format.SAMPLERS``, spelled out: importing the renderers package loads numba,
#: which ``--help`` must not (tests/test_sample_index.py checks the two agree).
SCENE_SAMPLERS = ("independent", "sobol")


def add_sampler_flag(parser, *, default=None) -> None:
    """--sampler independent|sobol: the built-in scenes' sampler (``SceneRenderer(sampler=)``).

    ``default`` None: the command tells "not given" apart (``adapt`` refuses it without --scene and on a resume,
    whose recorded spec decides)."""
    parser.add_argument("--sampler", choices=SCENE_SAMPLERS, default=default,
                        help="the built-in scene's sampler: independent uniform random numbers (default), or "
                             "each pixel's Owen-scrambled Sobol sequence over all dimensions, continued round "
                             "after round from the request's per-pixel sample index (docs/scenes.md#samplers)")


def finite_float(text: str) -> float:
    """An argparse type: a finite number (``nan``, ``inf`` and ``1e400`` are refused by the parser)."""
    try:
        x = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid number: {text!r}") from None
    if not math.isfinite(x):
        raise argparse.ArgumentTypeError(f"{text!r}: expected a finite number")
    return x


# ----------------------------------------------------------------- method options
def _methods(names=None) -> list[tuple[str, type]]:
    from ..methods import available_methods, method_class

    return [(name, method_class(name)) for name in (available_methods() if names is None else names)]


def _summary(cls) -> str:
    """The first line of a method's docstring, without its full stop."""
    lines = (cls.__doc__ or "").strip().splitlines()
    return lines[0].strip().rstrip(".") if lines else ""


def method_flags(taken, *, prefix: str = "--method-", methods=None) -> dict[str, str]:
    """``{option name: flag}`` of the methods' options.

    The flag is ``--NAME`` (``_`` shown as ``-``), or ``PREFIX + NAME``
    where the command has a flag ``--NAME`` of its own (``taken``).
    """
    flags = {}
    for _, cls in _methods(methods):
        for opt in cls.options:
            flag = opt.flag
            flags[opt.name] = flag if flag not in taken else prefix + opt.name.replace("_", "-")
    return flags


def _metavar(opt) -> str:
    return {int: "N", float: "X", bool: "BOOL"}.get(opt.type, "TEXT")


def _describe(opt, cls=None) -> str:
    others = ""
    if cls is not None and opt.name != "variant":
        others = "".join(f"; --variant {v}: {preset[opt.name]}" for v, preset in cls.variants.items()
                         if opt.name in preset and preset[opt.name] != opt.default)
    return f"{opt.help} (default: {opt.default}{others}; valid: {opt.expectation()})"


def add_method_options(parser, flags: dict, methods=None) -> None:
    """One ``--help`` group per method, holding its options.

    argparse registers a flag once: an option several methods share is
    registered in the group of the first of them, and every later group
    lists it (with that method's meaning) in its description.
    """
    registered = {}
    for name, cls in _methods(methods):
        if not cls.options:
            continue
        shared = [o for o in cls.options if o.name in registered]
        text = "".join(f"{flags[o.name]} {_metavar(o)}: the flag listed under {registered[o.name]} options; "
                       f"for {name}: {_describe(o, cls)}\n" for o in shared)
        group = parser.add_argument_group(f"{name} options ({_summary(cls)})", text or None)
        for opt in cls.options:
            if opt.name in registered:
                continue
            registered[opt.name] = name
            group.add_argument(flags[opt.name], dest=_DEST + opt.name, default=None, metavar=_metavar(opt),
                               help=_describe(opt, cls).replace("%", "%%"))


def given_method_options(args) -> dict:
    """``{option name: string}`` of the method flags given on the command line."""
    return {k[len(_DEST):]: v for k, v in vars(args).items() if k.startswith(_DEST) and v is not None}


def make_method(name: str, args, flags: dict):
    """The method ``name`` built from the method flags given (errors name the flag)."""
    from ..methods import get_method, method_class

    cls = method_class(name)
    own = [o.name for o in cls.options]
    given = given_method_options(args)
    for oname in given:
        if oname not in own:
            owners = [m for m, c in _methods() if any(o.name == oname for o in c.options)]
            raise InputError(f"method {name}", flags[oname],
                             f"does not apply to this method (an option of {', '.join(owners)}); "
                             f"{name}'s options: {', '.join(flags[o] for o in own) or '(none)'}")
    try:
        return get_method(name, **given)  # Option.convert validates the strings
    except InputError as exc:
        if exc.field in flags:
            raise InputError(exc.where, flags[exc.field], exc.problem) from None
        raise


# ----------------------------------------------------------------- pixel-statistics EXR inputs
#: ``(argparse dest, flag)`` of the EXR read flags (:func:`add_exr_read_flags`) that default to None.
EXR_READ_FLAGS = (("layout", "--layout"), ("mean", "--mean"), ("variance_channels", "--variance-channels"),
                  ("second_moment", "--second-moment"), ("count", "--count"), ("spp", "--spp"))


def add_exr_read_flags(parser, title: str, description: str):
    """The flags that say how to read a pixel-statistics EXR (``mcrecon.io.read_pixel_stats_exr``'s
    options), in a ``--help`` group ``title``; returns the group (a command adds its own flags to it)."""
    px = parser.add_argument_group(title, description)
    px.add_argument("--layout", default=None, choices=("pbrt-v4", "mitsuba-moment", "cycles"),  # pixel_exr.LAYOUTS
                    help="pbrt-v4 GBufferFilm (R,G,B + Variance.R/G/B), Mitsuba 3's moment integrator "
                         "(P.X/Y/Z + m2_P.X/Y/Z) or a Blender Cycles multilayer EXR (ViewLayer.Combined, or "
                         "ViewLayer.Noisy Image when Cycles denoised; no variance: pass several renders with "
                         "different seeds, a quoted glob such as 'shot.seed*.exr', a seed set, see "
                         "docs/pixel-statistics-inputs.md#seed-sets); default: detected from the channel names, or "
                         "the explicit mapping")
    px.add_argument("--mean", default=None, metavar="CHANNELS", help="mean channels, comma-separated (e.g. R,G,B); "
                    "alone, without --variance-channels: means only, as one render of a seed set")
    px.add_argument("--variance-channels", default=None, metavar="CHANNELS",
                    help="variance channels, comma-separated (e.g. Variance.R,Variance.G,Variance.B); "
                         "(--variance is AWR's estimator option)")
    px.add_argument("--variance-of", default="samples", choices=("samples", "mean"),
                    help="what --variance-channels hold: the variance of the samples (default) or of the pixel mean")
    px.add_argument("--second-moment", default=None, metavar="CHANNELS",
                    help="second-moment (E[x^2]) channels instead of variances; variance = n/(n-1) (m2 - mean^2)")
    px.add_argument("--count", default=None, metavar="N|CHANNEL|ATTRIBUTE",
                    help="samples per pixel: a number, a channel of per-pixel counts, or a header attribute")
    px.add_argument("--spp", default=None, metavar="N", help="samples per pixel (a number; same as --count N)")
    return px


def exr_read_options(args, *, given_only: bool = False) -> dict:
    """The read options of ``mcrecon.io.read_pixel_stats_exr`` the flags of :func:`add_exr_read_flags`
    give (``given_only``: only those given on the command line)."""
    opts = dict(layout=args.layout, mean=args.mean, variance=args.variance_channels,
                second_moment=args.second_moment, variance_of=args.variance_of, count=args.count, spp=args.spp)
    if given_only:
        opts = {k: v for k, v in opts.items() if v is not None and not (k == "variance_of" and v == "samples")}
    return opts


def exr_read_flags_given(args) -> list[str]:
    """The EXR read flags given on the command line."""
    given = [flag for dest, flag in EXR_READ_FLAGS if getattr(args, dest, None) is not None]
    return given + (["--variance-of"] if getattr(args, "variance_of", "samples") != "samples" else [])


# ----------------------------------------------------------------- outputs
def check_output(out, png=None, *, command: str = "mcrecon") -> None:
    """Refuse an output the run could not write, before any work is done (``command``: the sub-command,
    where a missing ``-o`` is reported)."""
    if out is None:
        raise InputError(command, "-o/--output", "missing: give the output EXR path")
    for p, suffix in ((Path(out), ".exr"), (None if png is None else Path(png), ".png")):
        if p is None:
            continue
        if p.suffix.lower() != suffix:
            raise InputError(str(p), "output", f"expected a path ending in {suffix}")
        _check_writable_parent(p, "output")


def _check_writable_parent(p: Path, field: str) -> None:
    """Refuse a path whose nearest existing ancestor is no writable directory (before any work is done)."""
    parent = p.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir() or not os.access(parent, os.W_OK):
        raise InputError(str(p), field, f"cannot be written: {parent} is not a writable directory")


@contextlib.contextmanager
def film_size_flag(size):
    """A Mitsuba scene file whose film differs from ``--size``: the bridge's error, in the command line's
    terms (it speaks of width/height and scene parameters, which the command line has not)."""
    try:
        yield
    except InputError as exc:
        film = re.search(r"film is (\d+x\d+)", exc.problem) if exc.field == "width/height" else None
        if film is None:
            raise
        raise InputError(exc.where, "--size", f"--size {size} but the scene's film is {film.group(1)}; omit "
                         "--size to render at the film's own size, or change the film in the scene file") from None


#: Suffixes of a sample log the commands write (HDF5).
LOG_SUFFIXES = (".h5", ".hdf5")


def check_log_output(path, *, flag: str = "-o/--output", overwrite: bool | None = False) -> None:
    """Refuse a sample log the command could not write, or should not: a path not ending in ``.h5``
    (``.hdf5``: an HDF5 log named ``x.exr`` fails every later command as "not an OpenEXR file"), and,
    unless ``overwrite`` (None: the caller has its own rule), an existing file: it may hold a run's
    samples, which a new log would replace without a word."""
    p = Path(path)
    if p.suffix.lower() not in LOG_SUFFIXES:
        raise InputError(str(p), flag, f"expected a path ending in {' or '.join(LOG_SUFFIXES)} (an HDF5 sample log)")
    if p.is_dir():
        raise InputError(str(p), flag, "is a directory; expected the path of a sample log to write")
    if overwrite is False and p.exists():
        raise InputError(str(p), flag, "exists (it may hold samples): give another path, or --overwrite to "
                         "replace it")
    _check_writable_parent(p, flag)


def write_outputs(image, out, *, channels, png, exposure, diagnostics=None, diag_dir=None,
                  counts=None) -> list[Path]:
    """Write the EXR, its PNG preview and the diagnostic maps; returns the paths written."""
    import numpy as np

    from ..io import write_exr, write_false_colour, write_png_preview

    out = Path(out)
    write_exr(out, image, channels=channels)
    written = [out]
    png = out.with_suffix(".png") if png is None else Path(png)
    write_png_preview(png, image, exposure=exposure)
    written.append(png)
    if diag_dir is not None:
        d = Path(diag_dir)
        maps = dict(diagnostics or {})
        if counts is not None:
            maps.setdefault("sample_density", counts)
        for name, m in maps.items():
            m = np.asarray(m)
            if m.ndim == 3 and m.shape[2] > 1:
                m = m.mean(axis=2)
            written.append(write_false_colour(d / f"{name}.png", m, title=name))  # with its colour bar
    return written


# ----------------------------------------------------------------- first-run notice
_PACKAGE = Path(__file__).resolve().parents[1]


def _numba_cache_dirs(source_dir: Path) -> list[Path]:
    """Where numba's ``cache=True`` may keep the kernels of a source directory (its locators, in order:
    ``NUMBA_CACHE_DIR``, which when set is the only one numba uses, else the ``__pycache__`` beside the
    source or the user-wide cache)."""
    import hashlib

    sub = f"{source_dir.name}_{hashlib.sha1(str(source_dir).encode()).hexdigest()}"
    if os.environ.get("NUMBA_CACHE_DIR"):
        return [Path(os.environ["NUMBA_CACHE_DIR"]) / sub]
    dirs = [source_dir / "__pycache__"]
    dirs.append(Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "numba" / sub)
    return dirs


def _kernel_files(part) -> list[Path]:
    """The package's source files at ``part`` (a file or a directory) that define cached numba kernels."""
    p = _PACKAGE / part
    files = []
    for f in sorted(p.rglob("*.py")) if p.is_dir() else [p]:
        try:
            if "cache=True" in f.read_text(encoding="utf-8"):
                files.append(f)
        except OSError:
            continue
    return files


def _cached(f: Path, tag: str) -> bool:
    """Whether numba keeps a kernel index of source file ``f`` at least as new as ``f``."""
    mtime = f.stat().st_mtime
    for d in _numba_cache_dirs(f.parent):
        try:
            with os.scandir(d) as it:
                if any(e.name.startswith(f"{f.stem}.") and e.name.endswith(f"{tag}.nbi") and e.stat().st_mtime >= mtime
                       for e in it):
                    return True
        except OSError:
            continue
    return False


def numba_cache_cold(parts) -> bool:
    """Whether a run using the code at ``parts`` (package paths: files, or directories such as
    ``methods/gem``) will compile numba kernels: some part defines cached kernels, and none of its files
    has a numba cache newer than itself (the first run after an install or an edit).  A cheap heuristic
    (file names and times; numba is not imported): a directory counts as compiled once any of its files
    is, since a run need not use every kernel of a method.
    """
    tag = f".py{sys.version_info[0]}{sys.version_info[1]}"
    for part in parts:
        files = _kernel_files(part)
        if files and not any(_cached(f, tag) for f in files):
            return True
    return False


def compile_notice(seconds: float | None = None, stream=None) -> None:
    """The one line saying that numba compiles kernels now (``seconds``: the expected time, ``~N s``)."""
    stream = sys.stderr if stream is None else stream
    stream.write(f"mcrecon: compiling kernels (first run only{f', ~{seconds:.0f} s' if seconds else ''})\n")
    stream.flush()


def jit_notice(parts, *, seconds: float | None = None, stream=None) -> bool:
    """On a terminal, one line on stderr before a run whose numba kernels are not cached yet.

    ``parts``: the package paths (files, directories) whose kernels the
    run uses (:func:`numba_cache_cold`).  Returns whether the notice was
    written.  Nothing happens when stderr is not a terminal (pipes, tests,
    batch jobs).
    """
    stream = sys.stderr if stream is None else stream
    try:
        if not stream.isatty():
            return False
    except (AttributeError, ValueError):
        return False
    if not numba_cache_cold(tuple(parts)):
        return False
    compile_notice(seconds, stream)
    return True


#: The compiled feature filters a method that reads features runs when the input carries them (the
#: demo's colour-only scene compiles neither: a first `denoise --method auto` of a log with features
#: compiled for 14 s without a word).
FEATURE_KERNELS = ("filters/regression.py", "filters/cross_bilateral.py")


def method_kernels(method, *, features: bool = False) -> tuple[str, ...]:
    """The package paths of a method's code: its sub-package (``methods/gem``) or its module; with
    ``features`` (the input carries them) and a method that reads them, the feature filters too."""
    mod = sys.modules.get(type(method).__module__)
    f = Path(getattr(mod, "__file__", "") or "")
    try:
        rel = f.resolve().relative_to(_PACKAGE)
    except ValueError:  # a method defined outside the package: nothing to check
        return ()
    own = (str(rel.parent),) if rel.parent != Path("methods") else (str(rel),)
    reads = getattr(getattr(method, "requires", None), "features", "none") != "none"
    return own + (FEATURE_KERNELS if features and reads else ())
