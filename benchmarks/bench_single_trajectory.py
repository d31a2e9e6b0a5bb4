"""Benchmark: one 5 s simulation of paper 004's arm.

`fd.rigs.flexible_link_joint_arm()` (two flexible links, two elastic joints, 8 coordinates),
bang-bang torque 0.2 N m with 0.5 s pulses on both joints, from rest, t = 0 to 5 s, output
at t = 5 s only. Runs:

- flexdyn, fixed-step RK4 at 1 ms (papers 002/004),
- flexdyn, adaptive Tsit5 at rtol 1e-8 (atol 1e-10),
- flexdyn, adaptive Tsit5 at rtol 1e-6 (atol 1e-8), a looser point of the same curve,
- peer: `scipy.integrate.solve_ivp(method="DOP853")` on `numpy_arm.NumpyChain`, a NumPy
  implementation of the same equations written for this benchmark (vectorised; it takes
  the assembled shape integrals as constants and forms M(Q), the velocity terms and the
  forces itself), at rtol 1e-3, 1e-6, 1e-8 and 1e-10; checked equal to `fd.accelerations` at
  random states (to ~1e-10 relative) before anything is timed,
- peer: `solve_ivp(DOP853)` at rtol 1e-8 calling flexdyn's jitted right-hand side
  (`fd.ChainVectorField`) wrapped as a NumPy function: SciPy's solver loop and per-call
  overhead with our right-hand side (skipped with `--no-jax-rhs-peer`).
  Like flexdyn's adaptive runs (which step onto the input's jumps), the peers integrate
  piecewise between the bang-bang switching times.

Each run is timed cold (first call in the process, compilation included) and warm: the
median of `--repeats` calls (`block_until_ready`) made round robin, one call of every run per
round (`_common.round_robin`), so that a slow spell of the machine falls on all runs alike; the
fastest call is reported too. The error is the largest absolute difference of the
coordinates `Q` (rad and m) at t = 5 s from a reference (diffrax Dopri8, rtol 1e-12,
atol 1e-14). Ratios are warm times relative to flexdyn's adaptive Tsit5 run at rtol 1e-8;
`compile [s]` is cold minus warm. *At matched accuracy*: for each flexdyn run, the NumPy
peer's warm time at the same error (log-log interpolation between its three runs; clamped,
and said so, outside their range) divided by the flexdyn run's warm time.

Usage: `python benchmarks/bench_single_trajectory.py [--repeats N] [--json results.json]`
"""

from __future__ import annotations

import argparse
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import diffrax  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from _common import environment, format_table, median_time, publish, round_robin, timed, warm_summary  # noqa: E402
from numpy_arm import NumpyChain  # noqa: E402

import flexdyn as fd  # noqa: E402  (enables float64)

T_END = 5.0  # s
RTOL, ATOL = 1e-8, 1e-10
LOOSE_RTOL, LOOSE_ATOL = 1e-6, 1e-8
PEER_RTOLS = (1e-3, 1e-6, 1e-8, 1e-10)  # NumPy peer, atol = rtol / 100
REF_RTOL, REF_ATOL = 1e-12, 1e-14


def problem():
    chain = fd.rigs.flexible_link_joint_arm()
    torque = fd.BangBang([0.2, 0.2], 0.5)
    y0 = fd.initial_state(chain, joint_angles=[0.0, 0.0])
    ts = jnp.array([0.0, T_END])
    return chain, torque, y0, ts


def flexdyn_runs(chain, torque, y0, ts):
    """The flexdyn runs, each called once (cold), and the reference; returns (rows, reference
    state at T_END). Each run's row holds its call under `"_call"` for the warm timing."""

    def run(**kwargs):
        def call():
            traj = fd.simulate(chain, y0, ts, torque, **kwargs)
            return jax.block_until_ready(traj)

        return call

    ref_traj, ref_cold = timed(run(solver=diffrax.Dopri8(), rtol=REF_RTOL, atol=REF_ATOL, max_steps=10**6))
    ref_Q = np.asarray(ref_traj.Q[-1])
    rows = []
    for name, kwargs in (
        ("flexdyn RK4, fixed dt = 1 ms", dict(dt=1e-3)),
        (f"flexdyn Tsit5, adaptive rtol {RTOL:g}", dict(rtol=RTOL, atol=ATOL)),
        (f"flexdyn Tsit5, adaptive rtol {LOOSE_RTOL:g}", dict(rtol=LOOSE_RTOL, atol=LOOSE_ATOL)),
    ):
        call = run(**kwargs)
        traj, cold = timed(call)
        rows.append(
            dict(
                run=name,
                _call=call,
                cold_s=cold,
                steps=int(traj.num_steps),
                rhs_evals=int(traj.num_steps) * (4 if "RK4" in name else 6),
                error_Q=float(np.max(np.abs(np.asarray(traj.Q[-1]) - ref_Q))),
            )
        )
    rows.append(
        dict(
            run=f"reference: flexdyn Dopri8, rtol {REF_RTOL:g}",
            cold_s=ref_cold,
            steps=int(ref_traj.num_steps),
            error_Q=0.0,
        )
    )
    return rows, ref_Q


def check_numpy_equations(chain, n_states=20, seed=0):
    """Largest relative difference of the NumPy peer's accelerations from `fd.accelerations`
    at random states and torques; raises if it is not ~1e-10 (the peer must be the same model)."""
    peer = NumpyChain.from_flexdyn(chain)
    asm = fd.assemble(chain)
    acc = jax.jit(lambda Q, Qd, tau: fd.accelerations(asm, Q, Qd, tau))
    rng = np.random.default_rng(seed)
    worst = 0.0
    for _ in range(n_states):
        Q, Qd = rng.normal(size=chain.n_dof), rng.normal(size=chain.n_dof)
        tau = rng.normal(size=chain.n_links)
        ours, theirs = np.asarray(acc(Q, Qd, tau)), peer.accelerations(Q, Qd, tau)
        worst = max(worst, float(np.max(np.abs(ours - theirs)) / np.max(np.abs(ours))))
    if not worst < 1e-9:
        raise AssertionError(f"NumPy peer differs from fd.accelerations by {worst:.2e} (relative)")
    return worst


def numpy_peer(chain, torque, y0, ref_Q, rtol):
    """solve_ivp(DOP853) on the NumPy equations (`numpy_arm`), piecewise between the jumps."""
    from scipy.integrate import solve_ivp

    peer = NumpyChain.from_flexdyn(chain)
    amplitude, width, start = (np.asarray(x, float) for x in (torque.amplitude, torque.width, torque.start))
    breaks = [0.0] + [float(t) for t in np.asarray(torque.jump_times()) if 0.0 < t < T_END] + [T_END]
    n = chain.n_dof

    def call():
        y, steps, nfev = np.asarray(y0, float), 0, 0
        for a, b in zip(breaks[:-1], breaks[1:]):
            # The torque is constant on each piece: its value at the piece's midpoint.
            s = 0.5 * (a + b) - start
            tau = amplitude * (1.0 if 0 <= s < width else -1.0 if width <= s < 2 * width else 0.0)
            sol = solve_ivp(lambda t, y: peer.rhs(t, y, tau), (a, b), y, method="DOP853", rtol=rtol, atol=rtol / 100)
            if not sol.success:
                raise RuntimeError(f"solve_ivp failed on [{a}, {b}]: {sol.message}")
            y, steps, nfev = sol.y[:, -1], steps + sol.t.size - 1, nfev + sol.nfev
        return y, steps, nfev

    (y_end, steps, nfev), cold = timed(call)
    y_probe = np.asarray(y0, float) + 1e-3
    tau = np.asarray(amplitude)
    per_eval = median_time(lambda: peer.rhs(0.1, y_probe, tau), 200)
    return dict(
        run=f"peer: NumPy equations + solve_ivp DOP853, rtol {rtol:g}",
        _call=call,
        cold_s=cold,
        steps=steps,
        rhs_evals=nfev,
        error_Q=float(np.max(np.abs(y_end[:n] - ref_Q))),
        rhs_call_us=1e6 * per_eval,
    )


def matched_speedups(rows):
    """For each flexdyn run: NumPy-peer warm time at the same error (log-log interpolation
    between the peer's runs) / the flexdyn run's warm time."""
    peers = sorted((r for r in rows if r["run"].startswith("peer: NumPy")), key=lambda r: r["error_Q"])
    log_e = np.log10([max(r["error_Q"], 1e-300) for r in peers])
    log_t = np.log10([r["warm_s"] for r in peers])
    out = []
    for r in rows:
        if not r["run"].startswith("flexdyn") or r.get("warm_s") is None:
            continue
        e = np.log10(max(r["error_Q"], 1e-300))
        clamped = bool(e < log_e[0] or e > log_e[-1])
        peer_s = float(10 ** np.interp(e, log_e, log_t))
        out.append(
            dict(
                run=r["run"],
                error_Q=r["error_Q"],
                warm_s=r["warm_s"],
                peer_warm_s=peer_s,
                speedup=peer_s / r["warm_s"],
                clamped=clamped,
            )
        )
    return out


def scipy_peer(chain, torque, y0, ref_Q):
    """solve_ivp(DOP853) on flexdyn's jitted right-hand side, piecewise between the input's jumps."""
    from scipy.integrate import solve_ivp

    field = fd.ChainVectorField(fd.assemble(chain), torque)
    rhs_jit = jax.jit(lambda t, y: field(t, y, None))

    def rhs(t, y):
        return np.asarray(rhs_jit(t, y))

    breaks = [0.0] + [float(t) for t in np.asarray(torque.jump_times()) if 0.0 < t < T_END] + [T_END]
    n = chain.n_dof

    def call():
        y, steps, nfev = np.asarray(y0), 0, 0
        for a, b in zip(breaks[:-1], breaks[1:]):
            sol = solve_ivp(rhs, (a, b), y, method="DOP853", rtol=RTOL, atol=ATOL)
            if not sol.success:
                raise RuntimeError(f"solve_ivp failed on [{a}, {b}]: {sol.message}")
            y, steps, nfev = sol.y[:, -1], steps + sol.t.size - 1, nfev + sol.nfev
        return y, steps, nfev

    (y_end, steps, nfev), cold = timed(call)
    y_probe = np.asarray(y0) + 1e-3
    per_eval = median_time(lambda: rhs(0.1, y_probe), 200)
    return dict(
        run=f"peer: scipy solve_ivp DOP853, rtol {RTOL:g} (our jitted RHS)",
        _call=call,
        cold_s=cold,
        steps=steps,
        rhs_evals=nfev,
        error_Q=float(np.max(np.abs(y_end[:n] - ref_Q))),
        rhs_call_us=1e6 * per_eval,
    )


COLUMNS = [
    ("run", "run", ""),
    ("cold_s", "cold [s]", ".3f"),
    ("warm_s", "warm [s]", ".4f"),
    ("min_s", "min [s]", ".4f"),
    ("ratio", "warm / Tsit5", ".2f"),
    ("compile_s", "compile [s]", ".2f"),
    ("steps", "steps", "d"),
    ("rhs_evals", "RHS evals", "d"),
    ("error_Q", "max abs error of Q(5 s)", ".2e"),
]
MATCHED_COLUMNS = [
    ("run", "flexdyn run", ""),
    ("error_Q", "its error", ".2e"),
    ("warm_s", "warm [s]", ".4f"),
    ("peer_warm_s", "NumPy peer at that error [s]", ".3f"),
    ("speedup", "speed-up (target >= 20)", ".1f"),
    ("clamped", "outside peer range", ""),
]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=5, help="round-robin rounds: warm calls per run (median)")
    parser.add_argument("--json", default=None, help="also write the results as JSON to this path")
    parser.add_argument("--no-jax-rhs-peer", action="store_true", help="skip the peer calling our jitted RHS")
    args = parser.parse_args(argv)

    env = environment()
    chain, torque, y0, ts = problem()
    check = check_numpy_equations(chain)
    rows, ref_Q = flexdyn_runs(chain, torque, y0, ts)
    numpy_rows = [numpy_peer(chain, torque, y0, ref_Q, rtol) for rtol in PEER_RTOLS]
    rows[3:3] = numpy_rows
    peer = None
    if not args.no_jax_rhs_peer:
        peer = scipy_peer(chain, torque, y0, ref_Q)
        rows.insert(3 + len(numpy_rows), peer)
    timed_rows = [r for r in rows if "_call" in r]
    samples = round_robin({r["run"]: r.pop("_call") for r in timed_rows}, args.repeats)
    for r in timed_rows:
        r.update(warm_summary(samples[r["run"]]))
        if r["run"].startswith("flexdyn"):
            r["compile_s"] = max(r["cold_s"] - r["warm_s"], 0.0)
    tsit5 = next(r for r in rows if r["run"] == f"flexdyn Tsit5, adaptive rtol {RTOL:g}")
    for r in rows:
        if r.get("warm_s") is not None:
            r["ratio"] = r["warm_s"] / tsit5["warm_s"]

    print("bench_single_trajectory: paper 004 arm (8 coordinates), bang-bang 0.2 N m / 0.5 s, 0 -> 5 s")
    matched = matched_speedups(rows)
    extra = dict(repeats=args.repeats, matched_accuracy=matched, numpy_peer_max_rel_difference=check)
    publish(args.json, "single_trajectory", env, rows, COLUMNS, **extra)
    print()
    print("At matched accuracy (NumPy peer's warm time interpolated to the flexdyn run's error):")
    print(format_table(matched, MATCHED_COLUMNS))
    print()
    print(
        f"NumPy peer: equal to fd.accelerations to {check:.1e} (max relative difference, 20 random states); "
        f"one call of its right-hand side costs {numpy_rows[0]['rhs_call_us']:.0f} us."
    )
    if peer is not None:
        print(
            f"Peer with our jitted RHS: one call from NumPy costs {peer['rhs_call_us']:.0f} us "
            "(dispatch + conversion included); it measures SciPy's solver overhead with flexdyn's RHS."
        )
    print(
        "Error: max over coordinates of |Q(5 s) - Q_ref(5 s)| (rad, m); reference diffrax Dopri8 at rtol "
        f"{REF_RTOL:g}, atol {REF_ATOL:g}. RHS evals for flexdyn are steps x stages (accepted steps only)."
    )
    return rows


if __name__ == "__main__":
    main()
