"""Robot plug-ins: a registration never silently replaces another robot, and a plug-in that lacks a method is told
which one."""

import pytest
import torch

from egcbf.robots import BUILTIN_ROBOTS, ROBOTS, Quadrotor, Robot, Unicycle, make_robot, register_robot
from egcbf.robots.checks import check_robot


def test_a_builtin_name_cannot_be_taken():
    class MyQuad(Unicycle):
        name = "quadrotor"

    with pytest.raises(ValueError, match=r"'quadrotor'.*built-in.*another name"):
        register_robot(MyQuad)
    with pytest.raises(ValueError, match="built-in"):
        register_robot(replace=True)(MyQuad)
    assert ROBOTS["quadrotor"] is Quadrotor and isinstance(make_robot("quadrotor"), Quadrotor)
    assert {"quadrotor", "unicycle"} <= BUILTIN_ROBOTS


def test_a_taken_user_name_needs_replace():
    class First(Unicycle):
        name = "rel-test-robot"

    class Second(Unicycle):
        name = "rel-test-robot"

    register_robot(First)
    try:
        register_robot(First)  # the same class again: fine
        with pytest.raises(ValueError, match=r"'rel-test-robot' is already registered.*First.*replace=True"):
            register_robot(Second)
        assert ROBOTS["rel-test-robot"] is First
        register_robot(replace=True)(Second)
        assert ROBOTS["rel-test-robot"] is Second and isinstance(make_robot("rel-test-robot"), Second)
    finally:
        del ROBOTS["rel-test-robot"]


def test_the_same_definition_run_again_re_registers():
    """A module imported anew (a notebook cell run twice, runpy) defines a new class object of the same name."""
    src = (
        "from egcbf.robots import Unicycle, register_robot\n"
        "@register_robot\nclass Again(Unicycle):\n    name = 'rel-again'\n"
    )
    try:
        for _ in range(2):
            exec(compile(src, "rel_again_module", "exec"), {"__name__": "rel_again_module"})
        assert ROBOTS["rel-again"].__qualname__ == "Again"
    finally:
        del ROBOTS["rel-again"]


@pytest.mark.parametrize("bad", [None, "", 3])
def test_a_robot_without_a_proper_name_is_refused(bad):
    class Nameless(Unicycle):
        name = bad

    with pytest.raises(TypeError, match="Robot subclass with a name"):
        register_robot(Nameless)


def test_a_missing_method_is_named():
    class Half(Unicycle):
        name = "rel-half"

        def heading(self, x):
            return Robot.heading(self, x)

    with pytest.raises(NotImplementedError, match=r"Half does not implement Robot\.heading\(\)"):
        check_robot(Half(), batch=4)
    with pytest.raises(NotImplementedError, match=r"Half does not implement Robot\.heading\(\)"):
        Half().heading(torch.zeros(1, Half.state_dim))
