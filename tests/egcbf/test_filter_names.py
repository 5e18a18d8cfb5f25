"""`METHOD:FILTER` names (egcbf.control.names): one parser for eval, demo and reproduce."""

import pytest
from hypothesis import given
from hypothesis import strategies as st

from egcbf.cli.demo import describe, out_dir
from egcbf.control import filters as filtered
from egcbf.control.names import FILTERS, filter_label, join_method, path_name, split_method

# a method name: anything without ':' (the parser leaves whether the method exists to its caller)
METHOD = st.text(st.characters(exclude_characters=":", exclude_categories=("Cs",)), min_size=1, max_size=12)


@given(method=METHOD, filt=st.sampled_from(FILTERS))
def test_split_inverts_join(method, filt):
    name = join_method(method, filt)
    assert split_method(name) == (method, filt)
    assert join_method(*split_method(name)) == name
    assert (":" in name) == (filt != "none") and ":" not in path_name(name)


@given(method=METHOD, filt=st.sampled_from(FILTERS[1:]))
def test_path_name_writes_the_colon_as_an_underscore(method, filt):
    assert path_name(join_method(method, filt)) == f"{method}_{filt}"


@pytest.mark.parametrize("name", ["egcbf+:", ":dcbf", ":", "egcbf+:dcbf:cbf", "egcbf+:bogus", "egcbf+:DCBF", ""])
def test_bad_names_are_refused_naming_the_filters(name):
    with pytest.raises(ValueError, match=r"METHOD:FILTER with FILTER one of \['cbf', 'prior', 'dcbf'\]"):
        split_method(name)


def test_join_refuses_what_split_could_not_read():
    for method, filt in (("", "dcbf"), ("a:b", "dcbf"), ("egcbf+", "bogus")):
        with pytest.raises(ValueError):
            join_method(method, filt)


def test_one_implementation_behind_eval_demo_and_reproduce(tmp_path):
    from egcbf.reproduce import LABELS

    assert filtered.FILTERS is FILTERS  # egcbf.control.filters re-exports the names' module
    assert split_method("egcbf+:none") == ("egcbf+", "none") and describe("egcbf+:none") == describe("egcbf+")
    assert describe("egcbf+:dcbf") == LABELS["egcbf+:dcbf"] == filter_label("EGCBF+", "dcbf") == "EGCBF+ + dCBF filter"
    assert LABELS["nominal:dcbf"] == "nominal + dCBF filter" and LABELS["egcbf+:cbf"] == "EGCBF+ + learned-CBF filter"
    assert out_dir(tmp_path, "egcbf+:dcbf") == tmp_path / "egcbf+_dcbf"
