"""Measurements behind DEFAULT_DT, DEFAULT_SUBSTEPS, DEFAULT_METHOD and DEFAULT_MAX_STEPS (docs/dynamics.md).

Run ``python -m egcbf.robots.quadrotor.calibrate [SECTION ...] [--episodes N] [--horizon S] [--dts DT ...]
[--device D]`` (all sections by default; the invocations behind docs/dynamics.md are in its "Reproduce" section).
It prints markdown tables:

1. ``accuracy``: the nominal closed loop under a zero-order hold of period ``dt``, integrated with each
   (method, substeps), against the same loop integrated with RK4 and 64 substeps (the "exact" ZOH solution);
2. ``openloop``: one ZOH step from random states (any attitude, fast body rates) under random controls;
3. ``rate``: the ZOH closed loop at each ``dt`` against a quasi-continuous loop (controller at 1 kHz);
4. ``timing``: time per step for 512 agents (and 8192 with a GPU ``--device``);
5. ``episode``: time to reach goals anywhere in [0, 4]^3 from rest, with the chosen defaults.
"""

from __future__ import annotations

import argparse
import math
import time

import torch

from .dynamics import DEFAULT_PARAMS, QuadrotorParams, hover_state, step, unpack
from .nominal import nominal_control


def sample_episodes(n: int, seed: int = 0, area: float = 4.0, dtype=torch.float64):
    """``n`` drones at rest at uniform points of ``[0, area]^3`` with uniform yaw, and uniform goals there."""
    gen = torch.Generator().manual_seed(seed)
    p0 = torch.rand(n, 3, generator=gen, dtype=dtype) * area
    goal = torch.rand(n, 3, generator=gen, dtype=dtype) * area
    yaw = (torch.rand(n, generator=gen, dtype=dtype) * 2 - 1) * math.pi
    return hover_state(p0, yaw), goal


@torch.no_grad()
def rollout(x0, goal, dt, steps, substeps, method="rk4", params: QuadrotorParams = DEFAULT_PARAMS, **ctrl):
    """Nominal closed loop under ZOH; returns states ``(steps + 1, *batch, 18)`` and controls ``(steps, *batch, 4)``."""
    xs, us = [x0], []
    x = x0
    for _ in range(steps):
        u = nominal_control(x, goal, params, **ctrl)
        x = step(x, u, dt, params, substeps=substeps, method=method)
        xs.append(x)
        us.append(u)
    return torch.stack(xs), torch.stack(us)


def _angle(ra, rb):
    """Rotation angle between two attitudes (rad): ``|Ra - Rb|_F = 2 sqrt(2) sin(angle / 2)`` (precise when small)."""
    d = (ra - rb).flatten(-2).norm(dim=-1) / (2 * math.sqrt(2))
    return 2 * torch.arcsin(d.clamp(max=1.0))


def traj_error(xa, xb):
    """Max position error (m) and max attitude error (rad) between two state trajectories."""
    pa, ra, _, _ = unpack(xa)
    pb, rb, _, _ = unpack(xb)
    return float((pa - pb).norm(dim=-1).max()), float(_angle(ra, rb).max())


def reach_stats(xs, goal, dt, radius=0.05):
    """First time (s) each drone is within ``2 radius`` of its goal (inf if never), and final distances."""
    d = (xs[..., :3] - goal).norm(dim=-1)  # (T+1, B)
    hit = d < 2 * radius
    first = torch.where(hit.any(0), hit.float().argmax(0).to(d.dtype) * dt, torch.full_like(d[0], math.inf))
    return first, d[-1]


def chatter(us):
    """Fraction of consecutive roll/pitch torque commands that flip sign while above 10% of their range."""
    t = us[..., :2]
    big = (t[1:].abs() > 1e-3) & (t[:-1].abs() > 1e-3)
    flip = (t[1:] * t[:-1] < 0) & big
    return float(flip.float().sum() / big.float().sum().clamp_min(1))


def accuracy_table(x0, goal, dts, settings, horizon, ref_substeps=32):
    print(f"## Integrator accuracy (vs RK4 x{ref_substeps} substeps at the same dt), max over {x0.shape[0]} episodes\n")
    print("| dt (s) | method | substeps | max pos err (m) | max att err (rad) |")
    print("|---|---|---|---|---|")
    for dt in dts:
        steps = round(horizon / dt)
        xr, _ = rollout(x0, goal, dt, steps, ref_substeps)
        for method, s in settings:
            xs, _ = rollout(x0, goal, dt, steps, s, method)
            ep, ea = traj_error(xs, xr)
            print(f"| {dt} | {method} | {s} | {ep:.1e} | {ea:.1e} |", flush=True)


def timing_table(settings, n=512, reps=300, device="cpu", dtype=torch.float32):
    """Median time per call over ``reps`` calls (one CPU thread on CPU; synchronized on CUDA)."""
    import statistics

    dev = torch.device(device)
    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)
    where = torch.cuda.get_device_name(dev) if dev.type == "cuda" else "1 CPU thread"
    print(f"\n## Cost: ms per call for {n} agents ({dtype}, {where}, median of {reps})\n")
    print("| call | substeps | ms |")
    print("|---|---|---|")
    x, goal = sample_episodes(n, 1, dtype=dtype)
    x, goal = x.to(dev), goal.to(dev)
    u = nominal_control(x, goal)

    def med(fn):
        for _ in range(10):
            fn()
        sync()
        ts = []
        for _ in range(reps):
            t0 = time.perf_counter()
            fn()
            sync()
            ts.append(time.perf_counter() - t0)
        return statistics.median(ts) * 1e3

    for method, k in settings:
        ms = med(lambda m=method, k=k: step(x, u, 0.025, substeps=k, method=m))
        print(f"| step {method} | {k} | {ms:.2f} |", flush=True)
    print(f"| nominal_control | - | {med(lambda: nominal_control(x, goal)):.2f} |", flush=True)


@torch.no_grad()
def openloop_table(n, dts, settings, max_rate=20.0, ref_substeps=64, seed=1):
    """One ZOH step from random states (any attitude, |w| <= max_rate) under random controls in the actuator box."""
    from .dynamics import DEFAULT_PARAMS as prm
    from .dynamics import state_from_parts
    from .so3 import so3_exp

    gen = torch.Generator().manual_seed(seed)
    f64 = torch.float64

    def r(*shape):
        return torch.rand(*shape, generator=gen, dtype=f64)

    def ball(scale):
        d = torch.randn(n, 3, generator=gen, dtype=f64)
        return d / d.norm(dim=-1, keepdim=True) * scale * r(n, 1) ** (1 / 3)

    x = state_from_parts(4 * r(n, 3), so3_exp(ball(math.pi)), ball(3.0), ball(max_rate))
    tmax = torch.tensor(prm.max_torque, dtype=f64)
    u = torch.cat(((2 * r(n, 3) - 1) * tmax, r(n, 1) * prm.max_thrust), dim=-1)
    print(f"\n## One step from random states (|w| <= {max_rate} rad/s), random controls in the box, {n} samples\n")
    print("| dt (s) | method | substeps | max pos err (m) | max att err (rad) | max w err (rad/s) |")
    print("|---|---|---|---|---|---|")
    for dt in dts:
        xr = step(x, u, dt, substeps=ref_substeps)
        for method, s in settings:
            y = step(x, u, dt, substeps=s, method=method)
            ep, ea = traj_error(y, xr)
            ew = float((y[..., 15:] - xr[..., 15:]).norm(dim=-1).max())
            print(f"| {dt} | {method} | {s} | {ep:.1e} | {ea:.1e} | {ew:.1e} |", flush=True)


def rate_table(x0, goal, dts, horizon, substeps=4, fine_dt=0.001):
    print(f"\n## Control rate: ZOH loop (RK4 x{substeps}) vs quasi-continuous loop (controller every {fine_dt} s)\n")
    print(
        "| dt (s) | max pos dev (m) | max att dev (rad) | torque sign-flip rate | max |w| (rad/s) "
        "| reach rate | median / max reach time (s) |"
    )
    print("|---|---|---|---|---|---|---|")
    xf, _ = rollout(x0, goal, fine_dt, round(horizon / fine_dt), 1)
    first_f, _ = reach_stats(xf, goal, fine_dt)
    print(
        f"| {fine_dt} (ref) | - | - | - | {float(xf[..., 15:].norm(dim=-1).max()):.1f} "
        f"| {float(first_f.isfinite().double().mean()):.3f} "
        f"| {float(first_f.median()):.2f} / {float(first_f.max()):.2f} |",
        flush=True,
    )
    for dt in dts:
        xr, ur = rollout(x0, goal, dt, round(horizon / dt), substeps)
        k = round(dt / fine_dt)
        xc = xf[::k]
        m = min(xc.shape[0], xr.shape[0])
        ep, ea = traj_error(xr[:m], xc[:m])
        first, _ = reach_stats(xr, goal, dt)
        fin = first[first.isfinite()]
        print(
            f"| {dt} | {ep:.2e} | {ea:.2e} | {chatter(ur):.3f} | {float(xr[..., 15:].norm(dim=-1).max()):.1f} "
            f"| {float(first.isfinite().double().mean()):.3f} "
            f"| {float(fin.median()):.2f} / {float(fin.max()):.2f} |",
            flush=True,
        )


def episode_table(n, dt, substeps, max_steps, seed=0, dtype=torch.float64):
    from .dynamics import DEFAULT_PARAMS as prm

    x0, goal = sample_episodes(n, seed=seed, dtype=dtype)
    xs, _ = rollout(x0, goal, dt, max_steps, substeps)
    first, final = reach_stats(xs, goal, dt, prm.radius)
    fin = first[first.isfinite()]
    q = torch.quantile(fin, torch.tensor([0.5, 0.9, 0.99], dtype=fin.dtype))
    print(f"\n## Episode length: {n} episodes, dt = {dt}, {max_steps} steps ({max_steps * dt:.2f} s)\n")
    print(f"- reach rate (distance < {2 * prm.radius} m at some step): {float(first.isfinite().double().mean()):.3f}")
    print(
        f"- time to reach: median {float(q[0]):.2f} s, 90% {float(q[1]):.2f} s, 99% {float(q[2]):.2f} s,"
        f" max {float(fin.max()):.2f} s (= {round(float(fin.max()) / dt)} steps)"
    )
    print(f"- final distance: median {float(final.median()):.2e} m, max {float(final.max()):.2e} m")
    print(f"- any NaN: {bool(torch.isnan(xs).any())}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument(
        "section",
        nargs="*",
        default=["accuracy", "openloop", "rate", "timing", "episode"],
        choices=["accuracy", "openloop", "rate", "timing", "episode"],
    )
    ap.add_argument("--episodes", type=int, default=100)
    ap.add_argument("--horizon", type=float, default=6.0, help="seconds simulated per episode")
    ap.add_argument("--dts", type=float, nargs="*", default=[0.01, 0.02, 0.025, 0.03, 0.04, 0.05])
    ap.add_argument("--device", default="cpu", help="device for the timing section")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    x0, goal = sample_episodes(args.episodes, seed=0)
    if "accuracy" in args.section:
        settings = [("rk4", 1), ("rk4", 2), ("rk4", 4), ("euler", 1), ("euler", 4), ("euler", 16)]
        accuracy_table(x0, goal, args.dts, settings, args.horizon)
    if "openloop" in args.section:
        settings = [("rk4", 1), ("rk4", 2), ("rk4", 4), ("euler", 1), ("euler", 4), ("euler", 16)]
        openloop_table(1000, args.dts, settings)
    if "rate" in args.section:
        rate_table(x0, goal, args.dts, args.horizon)
    if "timing" in args.section:
        settings = [("rk4", 1), ("rk4", 2), ("rk4", 4), ("euler", 1), ("euler", 4)]
        for n in (512, 8192) if args.device != "cpu" else (512,):
            timing_table(settings, n=n, device=args.device)
    if "episode" in args.section:
        from .dynamics import DEFAULT_DT, DEFAULT_MAX_STEPS, DEFAULT_SUBSTEPS

        episode_table(200, DEFAULT_DT, DEFAULT_SUBSTEPS, DEFAULT_MAX_STEPS)


if __name__ == "__main__":
    main()
