"""EpisodeStats: the paper's metrics on hand-made episodes."""

import pytest
import torch

from egcbf.env import EnvConfig, SwarmEnv
from egcbf.evaluate.metrics import EpisodeStats, summarize
from egcbf.robots.quadrotor import dynamics as dyn


def _info(coll, reach):
    return {"collision": torch.tensor(coll), "reached": torch.tensor(reach)}


def test_hand_made_episode():
    # 2 episodes x 3 agents x 4 steps
    F, T = False, True
    coll = [
        # env 0: agent 0 collides at steps 2 and 4 (two events), agent 1 never, agent 2 at step 4 (one event)
        [[F, F, F], [T, F, F], [F, F, F], [T, F, T]],
        # env 1: nobody collides
        [[F, F, F]] * 4,
    ]
    reach = [
        [[F, F, F], [F, T, F], [F, F, F], [F, F, F]],  # env 0: agent 1 reaches once
        [[T, T, T]] + [[F, F, F]] * 3,  # env 1: everyone at step 1
    ]
    st = EpisodeStats(2, 3)
    for t in range(4):
        c = torch.tensor([coll[0][t], coll[1][t]])
        r = torch.tensor([reach[0][t], reach[1][t]])
        u = torch.full((2, 3, 4), float(t))
        st.update({"collision": c, "reached": r}, u=u, u_ref=torch.zeros(2, 3, 4))
    per = st.per_episode()
    assert per["safe_rate"].tolist() == pytest.approx([1 / 3, 1.0])
    assert per["reach_rate"].tolist() == pytest.approx([1 / 3, 1.0])
    assert per["success_rate"].tolist() == pytest.approx([1 / 3, 1.0])  # agent 1 of env 0: safe and reached
    assert per["cost"].tolist() == pytest.approx([3 / 3, 0.0])
    assert per["collision_steps"].tolist() == pytest.approx([3 / 3, 0.0])
    # reward: -sum_t 4 t^2 = -4 (0 + 1 + 4 + 9) = -56 per agent
    assert per["reward"].tolist() == pytest.approx([-56.0, -56.0])
    row = st.result()
    assert row["num_agents"] == 3 and row["num_episodes"] == 2 and row["steps"] == 4
    assert row["safe_rate"] == pytest.approx(2 / 3)
    assert row["reach_rate"] == pytest.approx(2 / 3)
    assert row["success_rate"] == pytest.approx(2 / 3)
    assert (row["cost"], row["cost_min"], row["cost_max"]) == pytest.approx((0.5, 0.0, 1.0))
    assert row["reward"] == pytest.approx(-56.0)
    keys = {"num_agents", "safe_rate", "reach_rate", "success_rate", "cost", "cost_min", "cost_max", "reward"}
    assert keys <= set(row)
    assert all(0 <= row[k] <= 1 for k in ("safe_rate", "reach_rate", "success_rate"))


def test_sustained_contact_is_one_event_and_reach_is_sticky():
    st = EpisodeStats(1, 1)
    seq = [True] * 5 + [False] + [True]
    for i, c in enumerate(seq):
        st.update(_info([[c]], [[i == 2]]))
    per = st.per_episode()
    assert per["cost"].item() == 2 and per["reach_rate"].item() == 1 and per["success_rate"].item() == 0
    assert per["collision_steps"].item() == 6
    assert st.result()["reward"] == 0.0  # no controls given


def test_summarize_pools_batches():
    a, b = EpisodeStats(2, 4), EpisodeStats(1, 4)
    a.update(_info([[True, False, False, False]] * 2, [[True] * 4] * 2))
    b.update(_info([[False] * 4], [[False] * 4]))
    pooled = {k: torch.cat((a.per_episode()[k], b.per_episode()[k])) for k in a.per_episode()}
    row = summarize(pooled, 4)
    assert row["num_episodes"] == 3
    assert row["safe_rate"] == pytest.approx(10 / 12) and row["reach_rate"] == pytest.approx(8 / 12)
    assert (row["cost_min"], row["cost_max"]) == (0.0, 0.25)


def test_bad_inputs():
    st = EpisodeStats(1, 2)
    with pytest.raises(ValueError, match="collision"):
        st.update(_info([[True]], [[True, True]]))
    with pytest.raises(ValueError, match="both"):
        st.update(_info([[True, True]], [[True, True]]), u=torch.zeros(1, 2, 4))
    with pytest.raises(ValueError):
        EpisodeStats(0, 2)
    with pytest.raises(ValueError, match="at least one"):
        summarize({k: torch.zeros(0) for k in ("safe_rate", "reach_rate", "success_rate", "cost", "reward")}, 2)


def test_with_the_environment():
    cfg = EnvConfig(num_envs=2, num_agents=4, max_steps=5)
    env = SwarmEnv(cfg)
    s = env.reset(0)
    st = EpisodeStats(2, 4)
    u = dyn.hover_control(cfg.params, 2, 4)
    done = False
    while not done:
        s, info = env.step(s, u)
        st.update(info, u=info.u, u_ref=u)
        done = bool(info.done.all())
    row = st.result()
    assert row["safe_rate"] == 1.0 and row["reach_rate"] == 0.0 and row["cost"] == 0.0 and row["steps"] == 5
    assert row["reward"] == 0.0
