"""Each method option is written once, in its method's ``Option`` list: restoration's signatures and
docstrings, the command line's flags and ``mcrecon methods`` all come from it.

The tests read every registered method, and a method registered here with an option no one wrote
anywhere else shows that option in each of those places.
"""

from __future__ import annotations

import inspect
import json
import pydoc
import re
import typing

import pytest

import mcrecon
import mcrecon.methods as methods_registry
from mcrecon import restoration
from mcrecon.cli import build_parser, main
from mcrecon.methods import Method, Option, available_methods, method_class, register_method, variant_option

from helpers import run_cli

#: The registered methods without an array-level function: ci's offline image is box's (its stopping
#: rule is adaptive).
NO_FUNCTION = {"ci"}
#: A function's own keyword-only parameters, after the options.
OWN = {"gem": ["reference", "nonfinite"]}


def _functions():
    return [name for name in available_methods() if name not in NO_FUNCTION]


def test_every_registered_method_but_ci_has_its_function():
    assert restoration.__all__ == _functions()
    assert all(callable(getattr(restoration, n)) for n in restoration.__all__)


def _annotation(opt):
    t = typing.Literal[tuple(opt.choices)] if opt.choices is not None else opt.type
    return typing.Optional[t] if opt.allows_none else t


@pytest.mark.parametrize("name", _functions())
def test_the_signature_is_the_methods_options(name):
    sig = inspect.signature(getattr(restoration, name))
    options = method_class(name).options
    params = list(sig.parameters.values())
    assert params[0].name == "source" and params[0].kind is inspect.Parameter.POSITIONAL_ONLY
    assert [p.name for p in params[1:]] == [o.name for o in options] + OWN.get(name, ["nonfinite"])
    assert all(p.kind is inspect.Parameter.KEYWORD_ONLY for p in params[1:])
    for o in options:
        p = sig.parameters[o.name]
        assert p.default == o.default and type(p.default) is type(o.default), o.name
        assert p.annotation == _annotation(o), o.name
    assert sig.parameters["nonfinite"].default == "drop"


def _entry(doc: str, name: str) -> str:
    """The numpydoc entry of parameter ``name``: its line and the indented lines below it."""
    m = re.search(rf"^    {name} : .*\n((?:        .*\n)*)", doc, re.M)
    assert m, name
    return " ".join(m.group(0).split())


@pytest.mark.parametrize("name", _functions())
def test_the_docstring_lists_every_option_once_with_its_default_type_and_help(name):
    fn, cls = getattr(restoration, name), method_class(name)
    doc = fn.__doc__
    params = doc[doc.index("    Parameters\n"):doc.index("    Returns\n")]
    for o in cls.options:
        assert len(re.findall(rf"^    {o.name} : ", params, re.M)) == 1, o.name
        entry = _entry(params, o.name)
        assert f"(default {o.default!r}" in entry, entry
        assert " ".join(o.help.split())[1:40] in entry, entry   # the help, first letter capitalised
        kind = "{" if o.choices is not None else {float: "float", int: "int", str: "str", bool: "bool"}[o.type]
        assert entry.startswith(f"{o.name} : {kind}"), entry
        for v in cls.variants:
            preset = cls.option_default(o.name, v)
            if o.name != "variant" and preset != o.default:
                assert f"``variant={v!r}``: {preset!r}" in entry, (entry, v)
    # the sections the function's own text holds stay, in numpydoc order
    order = [doc.index(f"    {s}\n    {'-' * len(s)}\n") for s in ("Parameters", "Returns", "Raises", "Notes",
                                                                    "References", "Examples")]
    assert order == sorted(order)
    # what help() shows: every option with its default
    text = pydoc.render_doc(fn, renderer=pydoc.plaintext)
    for o in cls.options:
        assert f"{o.name}: " in text and f"{o.name} : " in text, o.name


@pytest.mark.parametrize("name", available_methods())
def test_the_class_docstring_leaves_the_options_to_them(name):
    """A method's class docstring holds its prose and references, not a second description of an option."""
    cls = method_class(name)
    doc = inspect.cleandoc(cls.__doc__ or "")
    names = {o.name for o in cls.options}
    written = [line for line in doc.splitlines()
               if re.match(r"^\w+(, \w+)* : ", line) and names & set(line.split(" : ")[0].split(", "))]
    assert written == [], written
    assert not re.search(r"^(Parameters|Options)\n-+$", doc, re.M)


def _help(command: str, capsys) -> str:
    code, out, err = run_cli([command, "--help"], capsys)
    assert code == 0, err
    return out


@pytest.mark.parametrize("command", ["reconstruct", "adapt"])
def test_the_cli_help_lists_every_flag_once(command, capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "200")  # one argument per line
    parser = build_parser(command)
    sub = next(a for a in parser._actions if hasattr(a, "choices") and isinstance(a.choices, dict)).choices[command]
    flags = sub.get_default("method_flags")
    text = _help(command, capsys)
    for name in available_methods():
        cls = method_class(name)
        if not cls.options:  # box: no group
            assert f"\n{name} options (" not in text
            continue
        group = text[text.index(f"\n{name} options ("):]
        group = group[:re.search(r"\n\w+ options \(|\Z", group[1:]).start() + 1]
        for o in cls.options:
            flag = flags[o.name]
            assert len([a for a in sub._actions if flag in a.option_strings]) == 1, flag
            assert len(re.findall(rf"^  {re.escape(flag)} [A-Z]+(?: |$)", text, re.M)) == 1, flag  # its argument
            assert re.search(rf"^  {re.escape(flag)} [A-Z]+(?:[ :]|$)", group, re.M), (name, flag)  # in its group


def test_mcrecon_methods_lists_every_option_once(capsys):
    assert main(["methods", "--json"]) == 0
    listed = {m["name"]: m for m in json.loads(capsys.readouterr().out)}
    assert sorted(listed) == sorted(available_methods())
    for name, m in listed.items():
        cls = method_class(name)
        assert [o["name"] for o in m["options"]] == [o.name for o in cls.options]
        assert [o["help"] for o in m["options"]] == [o.help for o in cls.options]
        assert main(["methods", name]) == 0
        out = capsys.readouterr().out
        for o in m["options"]:
            assert len(re.findall(rf"^  {re.escape(o['flag'])} ", out, re.M)) == 1, (name, o["flag"])


class _Blur(Method):
    """A blur that exists only in this test: its options are written here alone."""

    name = "blur_written_once"
    variants = {"robust": {}, "paper": {"radius": 3}}
    options = (variant_option(variants),
               Option("radius", int, 2, "blur radius in pixels", min=0),
               Option("weights", str, "flat", "kernel weights", choices=("flat", "tent")))

    def reconstruct_run(self, run, inputs):
        return inputs.stats.mean


def test_an_option_written_once_appears_everywhere(monkeypatch, capsys):
    monkeypatch.setattr(methods_registry, "METHODS", dict(methods_registry.METHODS))
    monkeypatch.setattr(methods_registry, "_CLASSES", dict(methods_registry._CLASSES))
    register_method(_Blur.name, _Blur)

    def blur_written_once(source, /, *, nonfinite="drop", **options):
        """A blur.

        Parameters
        ----------
        source : PixelStats
            The statistics.
        nonfinite : {'drop', 'zero', 'raise'}, optional
            Policy for NaN/Inf sample values.

        Returns
        -------
        image : ndarray
        """

    fn = restoration._method_function(blur_written_once)
    sig = inspect.signature(fn)
    assert list(sig.parameters) == ["source", "variant", "radius", "weights", "nonfinite"]
    assert sig.parameters["radius"].default == 2
    assert "radius : int, optional" in fn.__doc__ and "``variant='paper'``: 3" in fn.__doc__
    assert "weights : {'flat', 'tent'}, optional" in fn.__doc__
    assert main(["methods", _Blur.name]) == 0
    out = capsys.readouterr().out
    assert "--radius" in out and "blur radius in pixels" in out and "--variant paper: 3" in out
    text = _help("reconstruct", capsys)
    assert re.search(r"^  --radius N ", text, re.M) and "blur radius in pixels" in text
    with pytest.raises(mcrecon.InputError, match="unknown option; valid: radius, variant, weights"):
        fn(mcrecon.PixelStats.from_moments(*_moments()), sigma=1)


def _moments():
    import numpy as np

    return np.ones((4, 4, 3)), np.zeros((4, 4, 3)), 4
