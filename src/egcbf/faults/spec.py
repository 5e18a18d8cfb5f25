"""What can go wrong in a real swarm (:class:`FaultConfig`), its units, and the ``--faults`` spec.

Every fault is off by default (zero level); a :class:`FaultConfig` of all zeros simulates exactly the fault-free
world. Faults act where they would in a real swarm (:mod:`egcbf.faults.process`): the controller sees corrupted
observations and its commands are corrupted on their way to the rotors; the simulator, and so every safety metric,
keeps the true states.

Spec strings (``egcbf eval --faults``): comma-separated ``key=value`` pairs with the short names of
:data:`ALIASES` or the field names, optionally starting with ``default`` (the :data:`DEFAULT_FIELD` conditions,
overridden by what follows), e.g. ``"default"``, ``"pos=0.02,loss=0.2"``,
``"default,wind=1/0/0,noncoop_mode=straight"``; vectors are ``/``-separated. A path to a JSON file of field
names works too.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path

__all__ = [
    "ALIASES",
    "CHANNELS",
    "DEFAULT_FIELD",
    "HANDLING_FIELDS",
    "INERT_FIELDS",
    "MODIFIER_FIELDS",
    "NONCOOP_MODES",
    "RECEIVER_FIELDS",
    "FaultConfig",
    "given_fields",
    "parse_faults",
]

#: the perception channels (:class:`egcbf.faults.Sensing`) with the fault fields that act on each; the other faults
#: act on the state, the commands or the world, and reach every controller
CHANNELS = {"messages": ("msg_loss", "msg_burst", "msg_delay", "msg_hold", "msg_predict"),
            "lidar": ("lidar_noise", "lidar_drop")}  # fmt: skip

#: the receivers' message handling (not faults: what the agents do about lost and late messages; inert without
#: them)
RECEIVER_FIELDS = ("msg_hold", "msg_predict")

#: every field that is the agents' handling of a fault rather than a fault (inert without the fault it handles)
HANDLING_FIELDS = (*RECEIVER_FIELDS, "act_predict", "dist_obs")

#: the fields that shape a fault in time rather than set its level (inert without it): correlated estimation errors,
#: messages lost in runs
MODIFIER_FIELDS = ("noise_tau", "msg_burst")

#: every field that is no fault of its own: changes nothing while the faults it handles or shapes are off
INERT_FIELDS = (*HANDLING_FIELDS, *MODIFIER_FIELDS)


#: how a non-cooperative agent flies: ``"hover"`` holds its start position, ``"straight"`` flies the nominal
#: controller to its goal as if alone (a straight line at the nominal cruise speed)
NONCOOP_MODES = ("hover", "straight")


@dataclass(frozen=True)
class FaultConfig:
    """The fault levels of one evaluation (all zero: the fault-free world).

    Sensing (each agent's own estimate, which it also broadcasts to its neighbours):
        pos_noise: std (m) of the Gaussian error of each position coordinate, drawn fresh every step (see
            ``noise_tau``).
        vel_noise: std (m/s) of each velocity coordinate's error, likewise.
        noise_tau: not a level, the errors' memory (s; inert without ``pos_noise`` or ``vel_noise``): 0, the
            errors are white (fresh every step); ``> 0``, each coordinate's error is a first-order Gauss-Markov
            process with this time constant and the same std (``e_t = rho e_{t-1} + sqrt(1 - rho^2) std z_t``,
            ``rho = exp(-dt / noise_tau)``, started from its stationary law), as a real estimator's errors are.
        lidar_noise: std (m) of each LiDAR ray's range error.
        lidar_drop: probability that a LiDAR ray's return is lost (each ray, each step; the scan keeps the closest
            of the returns that arrive).

    Communication (each agent-to-agent edge of the graph carries the sender's broadcast state):
        msg_loss: probability that the message of an edge is lost in a step (the receiver does not see that
            neighbour in that step).
        msg_burst: not a level, how losses come (control steps; inert without ``msg_loss``): 0 (or 1), each step's
            message is lost independently; ``L >= 2``, each link's time is cut into blocks of ``L`` steps (a
            random phase per link) and each block is lost as a whole with probability ``msg_loss``: the same loss
            rate, in runs of ``L / (1 - msg_loss)`` steps on average (every run a multiple of ``L`` steps but at an
            episode's start), as a radio loses messages in bursts.
        msg_delay: control steps a message arrives late (the receiver sees the sender's estimate of ``msg_delay``
            steps ago, placed relative to its own current estimate).

    Receivers (not faults: how the agents handle lost and late messages; with neither loss nor delay they change
    nothing):
        msg_hold: control steps a receiver keeps using a neighbour's last received message while the newer ones are
            lost (0: a lost message is a neighbour missing from that step). A held message is as old as the steps
            since it was sent, plus ``msg_delay``.
        msg_predict: 1: every message is propagated to the present at the velocity it carries, over its age
            (``p + v age dt``, the rest of the state as sent); 0: used as it arrives.

    Actuation (per agent, drawn once per episode, acting on the command after the controller):
        gain: every control channel's gain is uniform in ``[1 - gain, 1 + gain]``.
        thrust_gain, torque_gain: the same on the robot's ``"thrust"`` / ``"torque"`` channels
            (:attr:`egcbf.robots.Robot.actuator_groups`; the quadrotor has both).
        torque_bias: each torque channel gets a constant bias uniform in ``[-torque_bias, torque_bias]`` (N m,
            body frame).
        act_delay: control steps between a command and its actuation (the first ``act_delay`` steps apply a
            hover command: the nominal control to the agent's own position).
        act_predict: not a fault, the agents' handling of ``act_delay`` (inert without it): 1: every agent
            commands for its state ``act_delay`` steps ahead, its estimate rolled through the robot's dynamics with
            its own commands still in flight (a Smith predictor, :class:`egcbf.faults.onboard.Onboard`; gain errors and
            wind unknown to it, or, with ``dist_obs``, their estimate added back), and broadcasts that prediction;
            0: it commands for its current estimate.
        dist_obs: not a fault, the agents' handling of disturbances (wind, gusts, the translational effect of gain
            and torque errors): 1: every agent
            estimates the acceleration acting on it beyond its model (its velocity estimate minus its model's
            prediction from its previous estimate under the command it knows acted, low-passed with time constant
            :data:`egcbf.faults.onboard.DIST_OBS_TAU`) and cancels it in its command
            (:meth:`egcbf.robots.Robot.reject_disturbance`: a disturbance observer,
            :class:`egcbf.faults.onboard.Onboard`);
            0: it does not. With exact estimates and no disturbance its estimate is exactly zero; under sensing noise
            alone it carries about ``vel_noise / 0.25 s`` of noise.

    Environment:
        wind: constant world acceleration (m/s^2, ``dim`` numbers, or empty for none) from wind force over mass.
        gust: std (m/s^2) per axis of a gust acceleration per environment, an Ornstein-Uhlenbeck process with
            time constant ``gust_tau`` (s) started from its stationary law.

    Agents:
        noncoop: fraction of agents (rounded, per environment, drawn once per episode) that ignore their
            controller and fly ``noncoop_mode`` (:data:`NONCOOP_MODES`); the others must avoid them. Metrics
            count the cooperative agents only (their collisions with non-cooperative ones count).
    """

    pos_noise: float = 0.0
    vel_noise: float = 0.0
    noise_tau: float = 0.0
    lidar_noise: float = 0.0
    lidar_drop: float = 0.0
    msg_loss: float = 0.0
    msg_burst: int = 0
    msg_delay: int = 0
    msg_hold: int = 0
    msg_predict: int = 0
    gain: float = 0.0
    thrust_gain: float = 0.0
    torque_gain: float = 0.0
    torque_bias: float = 0.0
    act_delay: int = 0
    act_predict: int = 0
    dist_obs: int = 0
    wind: tuple[float, ...] = ()
    gust: float = 0.0
    gust_tau: float = 1.0
    noncoop: float = 0.0
    noncoop_mode: str = "hover"

    def __post_init__(self) -> None:
        wind = tuple(float(w) for w in self.wind)
        object.__setattr__(self, "wind", () if all(w == 0.0 for w in wind) else wind)  # no wind is one config
        if self.msg_burst == 1 and not isinstance(self.msg_burst, bool):
            object.__setattr__(self, "msg_burst", 0)  # blocks of one step are independent losses: one config
        for name in ("pos_noise", "vel_noise", "noise_tau", "lidar_noise", "gain", "thrust_gain", "torque_gain",
                     "torque_bias", "gust"):  # fmt: skip
            _check(name, getattr(self, name), lambda v: v >= 0, "a finite number >= 0")
        for name in ("lidar_drop", "msg_loss", "noncoop"):
            _check(name, getattr(self, name), lambda v: 0 <= v <= 1, "a probability in [0, 1]")
        for name in ("gain", "thrust_gain", "torque_gain"):
            _check(name, getattr(self, name), lambda v: v < 1, "< 1 (a gain error of 100 % switches a motor off)")
        _check("gust_tau", self.gust_tau, lambda v: v > 0, "> 0")
        for name in ("msg_delay", "act_delay", "msg_hold", "msg_burst"):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < 0:
                raise ValueError(f"faults: {name} must be a whole number of control steps >= 0, got {v!r}")
        for name in ("msg_predict", "act_predict", "dist_obs"):
            v = getattr(self, name)
            if v not in (0, 1) or isinstance(v, bool):
                raise ValueError(f"faults: {name} must be 0 or 1, got {v!r}")
        if not all(math.isfinite(w) for w in self.wind):
            raise ValueError(f"faults: wind must be finite, got {self.wind}")
        if self.noncoop_mode not in NONCOOP_MODES:
            raise ValueError(f"faults: noncoop_mode must be one of {NONCOOP_MODES}, got {self.noncoop_mode!r}")

    # ------------------------------------------------------------------------------------------------ queries
    @property
    def is_null(self) -> bool:
        """Whether every fault is off (the fault-free world; the agents' handling of faults, :data:`HANDLING_FIELDS`,
        and the faults' shapes in time, :data:`MODIFIER_FIELDS`, then change nothing)."""
        zero = dataclasses.replace(FaultConfig(), noncoop_mode=self.noncoop_mode, gust_tau=self.gust_tau,
                                   **{name: getattr(self, name) for name in INERT_FIELDS})  # fmt: skip
        return self == zero

    @property
    def edge_faults(self) -> bool:
        """Whether a fault acts on what the agents perceive of each other and the obstacles (messages, LiDAR): it
        reaches only a controller that reads that channel (:func:`egcbf.faults.sensing.unread_faults`)."""
        return any(getattr(self, n) > 0 for names in CHANNELS.values() for n in names if n not in INERT_FIELDS)

    def without(self, names) -> FaultConfig:
        """This config with the fault fields ``names`` switched off."""
        return dataclasses.replace(self, **{name: getattr(FaultConfig(), name) for name in names})

    def active(self) -> dict:
        """The fields that differ from the fault-free default (for logs and result files)."""
        base = FaultConfig()
        return {
            f.name: getattr(self, f.name)
            for f in dataclasses.fields(self)
            if getattr(self, f.name) != getattr(base, f.name)
        }

    def spec(self) -> str:
        """The spec string of this config (:func:`parse_faults` reads it back); ``"none"`` when fault-free."""
        parts = []
        for k, v in self.active().items():
            parts.append(f"{k}={'/'.join(_number(w) for w in v) if isinstance(v, tuple) else v}")
        return ",".join(parts) or "none"

    def to_dict(self) -> dict:
        return {**dataclasses.asdict(self), "wind": list(self.wind)}


def _number(v: float) -> str:
    """``v`` short (``1``, ``0.5``) where that reads back exactly, else every digit it needs."""
    short = f"{v:g}"
    return short if float(short) == v else repr(float(v))


def _check(name: str, v, ok, what: str) -> None:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or not ok(v):
        raise ValueError(f"faults: {name} must be {what}, got {v!r}")


#: the "default field conditions" of docs/robustness.md: what a careful indoor flight with motion capture, a mesh
#: radio and off-the-shelf motors still has (1 cm / 2 cm/s estimation noise, 10 % of messages lost, one step of
#: latency, +-10 % thrust between motors, one agent in twenty hovering without cooperating)
DEFAULT_FIELD = FaultConfig(pos_noise=0.01, vel_noise=0.02, msg_loss=0.1, msg_delay=1, thrust_gain=0.1, noncoop=0.05)

#: short names of the spec string
ALIASES = {
    "pos": "pos_noise",
    "vel": "vel_noise",
    "lidar": "lidar_noise",
    "loss": "msg_loss",
    "burst": "msg_burst",
    "delay": "msg_delay",
    "hold": "msg_hold",
    "predict": "msg_predict",
}

_INT_FIELDS = ("msg_delay", "act_delay", "msg_hold", "msg_predict", "act_predict", "dist_obs", "msg_burst")


def parse_faults(spec: str | Path | FaultConfig | None) -> FaultConfig:
    """A :class:`FaultConfig` from a spec string (module doc), a JSON file, or ``None`` / ``"none"`` (no faults).

    Raises:
        ValueError: an unknown key (naming the known ones), a malformed pair or value, or a value out of range.
    """
    if spec is None or isinstance(spec, FaultConfig):
        return spec or FaultConfig()
    text = str(spec).strip()
    if text.endswith(".json") or (Path(text).suffix == ".json"):
        try:
            fields = json.loads(Path(text).read_text())
        except (OSError, json.JSONDecodeError) as err:
            raise ValueError(f"faults: cannot read {text}: {err}") from err
        if not isinstance(fields, dict):
            raise ValueError(f"faults: {text} must hold a JSON object of FaultConfig fields")
        named = {ALIASES.get(k, k) for k in fields}
        if len(named) < len(fields):
            raise ValueError(f"faults: {text} names a field twice (a short name and its field name)")
        return _build({}, {ALIASES.get(k, k): v for k, v in fields.items()}, text)
    if text in ("", "none"):
        return FaultConfig()
    base, pairs = {}, [p.strip() for p in text.split(",") if p.strip()]
    if pairs and pairs[0] == "default":
        base, pairs = DEFAULT_FIELD.to_dict(), pairs[1:]
    fields = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep:
            raise ValueError(f"faults: {pair!r} is not key=value (spec {text!r}; 'default' only comes first)")
        name = ALIASES.get(key.strip(), key.strip())
        fields[name] = value.strip()
    return _build(base, fields, text)


def given_fields(spec: str | Path | FaultConfig | None) -> frozenset[str]:
    """The :class:`FaultConfig` fields a spec sets itself (short names resolved), not through its leading
    ``default``: every set field of a :class:`FaultConfig` or JSON file, the ``key=value`` pairs of a string."""
    if spec is None:
        return frozenset()
    if isinstance(spec, FaultConfig):
        return frozenset(spec.active())
    text = str(spec).strip()
    if text.endswith(".json") or Path(text).suffix == ".json":
        return frozenset(parse_faults(text).active())
    pairs = [p.strip() for p in text.split(",") if p.strip() and p.strip() not in ("default", "none")]
    return frozenset(ALIASES.get(k.strip(), k.strip()) for k, _, _ in (p.partition("=") for p in pairs))


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _whole_number(name: str, value: str, source: str) -> int:
    """``value`` as a whole number (``"2"`` or ``"2.0"``), or a ValueError saying why not."""
    try:
        number = float(value)
    except ValueError as err:
        raise ValueError(f"faults: {name}={value!r} in {source!r} is not a number") from err
    if not number.is_integer():
        raise ValueError(f"faults: {name}={value!r} in {source!r} is not a whole number")
    return int(number)


def _build(base: dict, fields: dict, source: str) -> FaultConfig:
    known = {f.name for f in dataclasses.fields(FaultConfig)}
    unknown = sorted(set(fields) - known)
    if unknown:
        names = sorted(known | set(ALIASES))
        raise ValueError(f"faults: unknown {unknown} in {source!r}; known: {names}")
    out = dict(base)
    for name, value in fields.items():
        if not isinstance(value, str):  # a JSON file's numbers: each field's type, so a spec has one spelling
            if name == "wind":
                value = tuple(float(w) if _is_number(w) else w for w in value)
            elif _is_number(value) and name in _INT_FIELDS and float(value).is_integer():
                value = int(value)
            elif _is_number(value) and name not in _INT_FIELDS:
                value = float(value)
            out[name] = value
            continue
        if name in _INT_FIELDS:
            out[name] = _whole_number(name, value, source)
            continue
        try:
            if name == "wind":
                out[name] = tuple(float(w) for w in value.split("/")) if value else ()
            elif name == "noncoop_mode":
                out[name] = value
            else:
                out[name] = float(value)
        except ValueError as err:
            raise ValueError(f"faults: {name}={value!r} in {source!r} is not a number") from err
    if "wind" in out:
        out["wind"] = tuple(out["wind"])
    return FaultConfig(**out)
