"""errors.the_one: the one candidate, or a one-line InputError naming the fix."""

import pytest

from mcrecon.errors import InputError, the_one


def test_one_candidate_is_returned():
    assert the_one("f.exr", "mean", iter(["ViewLayer"]), none="x", several="y") == "ViewLayer"


def test_none_and_several_name_the_file_field_and_choices():
    with pytest.raises(InputError) as e:
        the_one("f.exr", "mean", [], none="no image; channels present: R", several="unused")
    assert str(e.value) == "f.exr: mean: no image; channels present: R"
    with pytest.raises(InputError) as e:
        the_one("f.exr", "mean", ["Fg", "Bg"], none="unused",
                several="several layers ({found}): choose one with --mean {first}.R")
    assert str(e.value) == "f.exr: mean: several layers (Fg, Bg): choose one with --mean Fg.R"
