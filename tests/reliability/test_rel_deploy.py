"""The per-agent controller a robot runs (``egcbf.deploy.agent``) refuses what the simulator refuses: an attitude that
is not a rotation (all zeros, ``2 I``), and a controller that would hear no neighbour (``max_neighbours = 0``)."""

from pathlib import Path

import pytest
import torch

from egcbf.deploy.agent import AgentController

ROOT = Path(__file__).resolve().parents[2] / "checkpoints" / "egcbf+"


@pytest.fixture(scope="module")
def ctrl():
    return AgentController.from_checkpoint(ROOT)


def _state(R):
    x = torch.zeros(18)
    x[0:3] = torch.tensor([1.0, 1.0, 1.0])
    x[3:12] = R.reshape(9)
    return x


def test_a_rotation_is_accepted(ctrl):
    u, _ = ctrl(_state(torch.eye(3)), torch.tensor([2.0, 1.0, 1.0]), torch.zeros(0, 18), torch.zeros(0, 3))
    assert u.shape == (4,) and torch.isfinite(u).all()


@pytest.mark.parametrize("R", [torch.zeros(3, 3), 2 * torch.eye(3)], ids=["zeros", "2I"])
def test_an_attitude_that_is_not_a_rotation_is_refused(ctrl, R):
    with pytest.raises(ValueError, match=r"state: .*R is not a rotation"):
        ctrl(_state(R), torch.tensor([2.0, 1.0, 1.0]), torch.zeros(0, 18), torch.zeros(0, 3))


@pytest.mark.parametrize("bad", [0, -1, 2.5, True])
def test_a_controller_that_hears_no_neighbour_is_refused(bad):
    with pytest.raises(ValueError, match="max_neighbours must be an integer >= 1"):
        AgentController.from_checkpoint(ROOT, max_neighbours=bad)
