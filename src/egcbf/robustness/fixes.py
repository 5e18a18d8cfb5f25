"""The report's "Fixes" sections: for each agent-side fix (the receivers' hold and prediction, the actuation
predictor, the disturbance observer), every controller it reaches at one level of its axis, without and with it,
paired over the same scenes."""

from __future__ import annotations

from ..faults import DEFAULT_FIELD
from ..faults.onboard import DIST_OBS_TAU
from ..reproduce.paper import LABELS
from .cells import before_after
from .plan import RECEIVER_HOLD, RobustnessConfig, axis

__all__ = ["fix_rows", "fix_sections"]


def fix_rows(
    cfg: RobustnessConfig, cells: dict, before: str, after: str, what: str, change: str = "with the fix"
) -> list[str]:
    """The table of a fix: every controller the fix reaches, level ``before`` against ``after`` (the same level
    with the fix, or another ``change`` of it; paired over the same scenes), ``what`` naming the level in the
    header."""
    lines = [
        f"| controller | N | obstacles | safe % ({what}) | safe % ({what}, {change}) | change, points "
        f"[95 % CI] | success % ({what}) | success % ({change}) |",
        "|---|---|---|---|---|---|---|---|",
    ]  # fmt: skip
    for m in cfg.controllers:
        if cfg.cell_spec(m, after) == cfg.cell_spec(m, before):
            continue  # perceives none of what the fix handles: it changes nothing for it
        for n in cfg.num_agents:
            for k in (0, cfg.obstacles):
                pair = before_after(cells.get((m, before, n, k)), cells.get((m, after, n, k)))
                lines.append(f"| {LABELS.get(m, m)} | {n} | {k} | {pair} |")
    return lines


def _compared(cfg: RobustnessConfig, name: str) -> tuple[str, str] | None:
    """The fix axis ``name``'s compared pair of specs (:meth:`Axis.compared`) if ``cfg`` sweeps it and its axis."""
    a = axis(name)
    return a.compared() if name in cfg.axes and a.fixes in cfg.axes else None


def _receivers_section(cfg: RobustnessConfig, cells: dict) -> list[str]:
    """The fix of the message faults: the default field conditions with the receivers holding a
    lost neighbour's last message and predicting every message over its age, against the same conditions without,
    for every controller that reads messages (paired over the same scenes)."""
    pair = _compared(cfg, "field_receivers")
    if pair is None:
        return []
    before, after = pair
    return [
        "## Fixes: what the receivers do about lost and late messages",
        "",
        "A lost message removes a neighbour from the receiver's graph (and from its QP rows) for that step, and a "
        "late one shows it where it was. Neither needs a new controller: each receiver can keep using a "
        f"neighbour's last message for a few steps (`msg_hold`, here {RECEIVER_HOLD} steps) and move every "
        "message on at the velocity it carries over its age (`msg_predict`: constant-velocity dead reckoning, "
        "`p + v age dt`). The receivers' axes (`field_receivers`, `loss_receivers`, "
        "`delay_receivers`) repeat the message axes with both; the table is the default field conditions without "
        "and with them (the same scenes; the change is the paired difference, after minus before).",
        "",
        *fix_rows(cfg, cells, before, after, "default"),
        "",
    ]  # fmt: skip


def _actuation_section(cfg: RobustnessConfig, cells: dict) -> list[str]:
    """The fix of actuation delay: two steps of delay with every agent commanding for its state
    predicted over the delay, against the same delay without (every controller; paired over the same scenes)."""
    pair = _compared(cfg, "act_delay_predict")
    if pair is None:
        return []
    before, after = pair
    delay = axis("act_delay_predict").compared_level()
    return [
        "## Fixes: commanding for the state the command will act on",
        "",
        "A command that acts `act_delay` control steps late was computed for a state the agent has left. The "
        "quadrotor's command is its body torques and collective thrust (`u = [tau, F3]`), so the delay acts inside "
        "the attitude loop, as on a vehicle whose torques are computed off board; a vehicle with its own fast "
        "attitude controller sees the delay on its setpoint only, which is milder (this model is the harsher "
        "one). Without a fix one step makes the attitude loop oscillate and two flip the agents, which then fall "
        "or fly out of the arena (tests/egcbf/test_faults.py, `test_actuation_delay_destabilizes_the_attitude_"
        "loop_and_the_predictor_restores_it`): those agents touch no one, so the safe rates of these cells count "
        "agents out of control as safe; read them with the success rates. The agent knows its delay and the "
        "commands it has sent, so it can roll its estimate forward through its own dynamics over them and command "
        "for that predicted state (`act_predict`: a Smith predictor; it knows neither gain errors nor wind, unless "
        "`dist_obs` measures them; it broadcasts the prediction, so the whole swarm acts on the same future). The "
        f"`act_delay_predict` axis repeats the actuation-delay axis with it; the table is {delay:g} steps of delay "
        "without and with it (the same scenes; after minus before). With the delay the only fault the prediction "
        "is exact, so this axis is the fix's ceiling; under noise, gain errors or wind as well it is approximate "
        f"(`egcbf eval --faults default,act_delay={delay:g},act_predict=1` measures that case).",
        "",
        *fix_rows(cfg, cells, before, after, f"`{before}`"),
        "",
    ]  # fmt: skip


def _disturbance_section(cfg: RobustnessConfig, cells: dict) -> list[str]:
    """The fix of wind and thrust gain errors: the compared wind and thrust gain levels with every
    agent's disturbance observer, against the same faults without (every controller; paired over the same
    scenes)."""
    tables = []
    for pair in (_compared(cfg, "wind_observer"), _compared(cfg, "thrust_observer")):
        if pair is not None:
            tables += [*fix_rows(cfg, cells, pair[0], pair[1], f"`{pair[0]}`"), ""]
    if not tables:
        return []
    pair = _compared(cfg, "field_fixes")
    if pair is not None:
        before, after = pair
        tables += [
            "The default field conditions' fixes at once (the receivers' hold and prediction, and the disturbance "
            f"observer against their +-{100 * DEFAULT_FIELD.thrust_gain:g} % thrust), against the same conditions "
            "without (`field_fixes`; the observer differentiates noisy velocity estimates, so this is where it "
            "could cost safety):",
            "",
            *fix_rows(cfg, cells, before, after, "default"),
            "",
        ]  # fmt: skip
    return [
        "## Fixes: cancelling the wind and the thrust errors",
        "",
        "Wind and a thrust gain error push every agent off what its controller commands: each controller's "
        "position loop is proportional, so a steady push leaves a steady offset, and an agent held off its goal by "
        "more than the goal radius never arrives; a QP that takes the commanded acceleration for the realized one "
        "can also be pushed closer to a neighbour than it planned (the wind and thrust figures below, and the "
        "tables). The agent can measure what pushes it: its velocity estimate against what its own model predicts "
        "from its previous estimate under the command it knows acted, low-passed over "
        f"{DIST_OBS_TAU:g} s, is the acceleration acting on it beyond its model; it then cancels that in its "
        "command (`dist_obs`: a disturbance observer; `Robot.reject_disturbance` turns the "
        "quadrotor's thrust vector by `-m d`, the attitude loop's own answer to the lowered target, to first "
        "order). The `wind_observer` and `thrust_observer` axes repeat those axes with it; the tables are "
        f"{axis('wind_observer').compared_level():g} m/s^2 of wind (with gusts of half that) and "
        f"+-{100 * axis('thrust_observer').compared_level():g} % thrust gain, without and with it (the same "
        "scenes; after minus before). It reads velocity estimates, so sensing noise enters it (about "
        f"`vel_noise / {DIST_OBS_TAU:g} s`: "
        f"{DEFAULT_FIELD.vel_noise / DIST_OBS_TAU:.2g} m/s^2 at the default field's "
        f"{100 * DEFAULT_FIELD.vel_noise:g} cm/s). Both agent-side fixes, this one and the actuation predictor, "
        "are `egcbf.faults.onboard.Onboard`, which a robot runs around its own controller (docs/deploy.md, "
        "\"Latency and wind on board\"; `examples/onboard_robot.py`).",
        "",
        *tables,
    ]  # fmt: skip


def fix_sections(cfg: RobustnessConfig, cells: dict) -> list[str]:
    """Every "Fixes" section whose axes ``cfg`` sweeps (markdown lines)."""
    return [*_receivers_section(cfg, cells), *_actuation_section(cfg, cells), *_disturbance_section(cfg, cells)]
