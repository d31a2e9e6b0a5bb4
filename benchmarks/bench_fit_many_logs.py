"""Benchmark: fitting many logs at once, the block-arrow Jacobian vs the dense one.

A joint fit of `L` logs has shared physical parameters (`P` of them) and per-log
nuisances (`k` per log: free initial-state entries, sensor offsets). The Jacobian is
block-arrow shaped (`identify.residuals`). The generic forward-mode Jacobian (`jax.jacfwd`
of the whole residual vector, what `identify` did before and what a user would write)
pushes all `P + L k` column tangents through every log's solve: `L (P + L k)` tangent
solves, quadratic in `L`. `identify.residuals.log_jacobian` carries `P + k_y0` tangents per
log (the offsets' columns are closed-form): linear in `L`.

Scenario: the 4-parameter flexible-arm problem of `bench_fit_convergence.py` (one
flexible link, horizontal plane; free EI, joint damping, hub inertia, payload mass), `L`
logs of 1.2 s at 4 ms (`theta1`, `tip1`, 1 % noise), each driven by the scenario's
doublets scaled by 1 + 0.1 l, each with its initial angle and rate and a `tip1` offset
free (k = 3), Tsit5 at a constant 1 ms step (what a fit stage integrates with).

Rows, per `L`:
- `jacobian`: residuals and whole Jacobian at the guess; ours (`log_jacobian` + `dense`)
  vs the peer (`jax.jacfwd` of `identify.residuals.residuals`) in the same process; the
  ratio column is the warm time over one residual evaluation.
- `LM solve`: one Levenberg-Marquardt solve (the fit's settings, single shooting from a
  guess 10 % off): ours (`identify.fit._residual_fn_lm`, with the block-by-block step of
  `identify.block_lm` from `identify.fit.BLOCK_SOLVE_MIN_LOGS` logs on), ours with
  optimistix's dense QR step, and the peer: optimistix's `LevenbergMarquardt` with the dense
  rule (a custom JVP materialising `jax.jacfwd` once per linearisation, the rule `identify`
  used before). All take the same iterates; steps and final costs are reported.
- `covariance`: the standard errors at a point (what `identify.fit` does once at the
  optimum): ours (`identify.fit._covariance_at`: from `BLOCK_SOLVE_MIN_LOGS` logs on, the
  Jacobian's blocks and `identify.covariance.blocked`, no dense Jacobian) vs the dense path
  (`_jacobian_natural`'s dense `J`, its SVD: `identify.covariance.dense`), with the dense
  `J`'s size and the largest relative difference of the standard errors.

`--per-log payload.mass`: that parameter is fitted per log (`identify.Parameter.per_log`,
`L` columns instead of one). Ours carries each log's own column's tangent through its
solve (`P - 1 + 1 + k_y0` per log), the peer every log's (`P - 1 + L + L k` per log).

Usage: `python benchmarks/bench_fit_many_logs.py [--logs 1,2,4,8,16,32] [--lm-logs 2,16] [--cov-logs 16,64]
[--per-log NAME] [--repeats 3] [--json out.json]`
"""

from __future__ import annotations

import argparse
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import equinox as eqx  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import optimistix as optx  # noqa: E402
from _common import environment, median_time, publish, timed  # noqa: E402
from bench_fit_convergence import TRUTH, scenario  # noqa: E402

import flexdyn as fd  # noqa: E402, F401  (enables float64)
import identify  # noqa: E402
import identify._fit.jacobian as jacobian_module
import identify._fit.levenberg_marquardt as levenberg_marquardt_module
import identify._model.parameters as parameters_module
import identify._model.problem as problem_module
from identify._model.residuals import log_jacobian, residuals  # noqa: E402
from identify._model.variables import Variables  # noqa: E402

COLUMNS = [
    ("run", "run", ""),
    ("logs", "logs", "d"),
    ("columns", "Jacobian columns", "d"),
    ("cold_s", "cold [s]", ".2f"),
    ("warm_s", "warm [s]", ".4f"),
    ("ratio", "warm / residual", ".1f"),
    ("speedup", "speed-up vs dense", ".2f"),
    ("steps", "LM steps", "d"),
    ("dense_mb", "dense J [MB]", ".0f"),
    ("cost", "final cost", ".6g"),
]
STEP = 1e-3


def problem(L: int, per_log: str = ""):
    chain, t, tau, noise = scenario(modes=1, duration=1.2, dt=4e-3)
    logs = [
        identify.simulate_log(
            chain,
            t,
            torque=tau * (1 + 0.1 * l),
            channels=("theta1", "tip1"),
            noise=noise,
            rng=np.random.default_rng(100 + l),
            initial={"theta1": 0.01 * l},
            fit_initial=("theta1", "theta1_rate"),
            offsets=("tip1",),
            name=f"log{l}",
        )
        for l in range(L)
    ]
    params = [
        identify.Parameter(n, v * (1.1 if i % 2 else 1 / 1.1), per_log=n == per_log)
        for i, (n, v) in enumerate(TRUTH.items())
    ]
    p = identify.make_problem(chain, params, logs, noise)
    x = jnp.asarray(parameters_module.x_from_theta(p, problem_module.guesses_of(p, params)))
    z = Variables(
        offset=jnp.zeros(len(p.offset_free)),
        phys=jnp.asarray(parameters_module.z_from_x(p, np.asarray(x))),
        y0=jnp.asarray([p.y0_known[a, b] for a, b in p.y0_free]),
    )
    return p, x, z


def dense_rule(fn):
    """The peer's linearisation: `jax.jacfwd` of the whole residual vector, once per
    linearisation, and the linear map a product with it."""

    @eqx.filter_custom_jvp
    def wrapped(z, args):
        return fn(z, args)

    @wrapped.def_jvp
    def wrapped_jvp(primals, tangents):
        z, args = primals
        tz, _ = tangents
        J, r = jax.jacfwd(lambda z_: (lambda out: (out, out))(fn(z_, args)), has_aux=True)(z)
        dr = jnp.zeros_like(r)
        for key in ("offset", "phys", "y0"):
            if getattr(tz, key) is not None:
                dr = dr + getattr(J, key).reshape(r.shape[0], -1) @ getattr(tz, key).reshape(-1)
        return r, dr

    return wrapped


@eqx.filter_jit
def jac_ours(p, x, z):
    jac = log_jacobian(p, lambda x_: parameters_module.theta_from_x(p, x_), x, z.y0, z.offset, p.sigma, None, STEP)
    return jac.r.reshape(-1), jac.dense(len(p.y0_free), len(p.offset_free))


@eqx.filter_jit
def jac_dense(p, x, z):
    def fn(v):
        return residuals(p, parameters_module.theta_from_x(p, v["x"]), v["y0"], v["offset"], p.sigma, None, STEP)[0]

    v = {"x": x, "y0": z.y0, "offset": z.offset}
    J = jax.jacfwd(fn)(v)
    return fn(v), jnp.concatenate([J["x"], J["y0"], J["offset"]], axis=1)


@eqx.filter_jit
def residual(p, x, z):
    return residuals(p, parameters_module.theta_from_x(p, x), z.y0, z.offset, p.sigma, None, STEP)[0]


_dense_lm = dense_rule(levenberg_marquardt_module._residual_fn)


def lm(rule, block: bool):
    @eqx.filter_jit
    def solve(p, z0):
        if block:  # what `identify.fit` uses: the block solve from BLOCK_SOLVE_MIN_LOGS logs on
            solver = levenberg_marquardt_module._levenberg_marquardt(p, 1e-3, 1e-10)
        else:
            solver = optx.LevenbergMarquardt(rtol=1e-3, atol=1e-10, norm=optx.rms_norm)
        args = (p, p.sigma, None, STEP)
        sol = optx.least_squares(rule, solver, z0, args=args, max_steps=100, throw=False)
        return sol.value, sol.stats["num_steps"], jnp.sum(levenberg_marquardt_module._residual_fn(sol.value, args) ** 2)

    return solve


def covariance_rows(L: int, repeats: int, per_log: str = ""):
    p, x, z = problem(L, per_log)
    ncol = len(p.names) + len(p.y0_free) + len(p.offset_free)

    def dense():
        r, J, _ = jacobian_module._jacobian_natural(p, x, z.y0, z.offset, p.sigma, STEP)
        return jacobian_module._dense_covariance(p, r, J), J.nbytes

    out = {}
    for name, fn in (
        ("ours", lambda: (jacobian_module._covariance_at(p, x, z, p.sigma, STEP)[0], None)),
        ("dense", dense),
    ):
        (cov, nbytes), cold = timed(fn)
        out[name] = (cov, nbytes, cold, median_time(fn, repeats))
    a, b = out["ours"][0].std_errors, out["dense"][0].std_errors
    err = float(np.max(np.abs(a - b) / np.abs(b)))
    print(
        f"  {L:3d} logs: covariance ours {out['ours'][3]:.3f} s, dense {out['dense'][3]:.3f} s "
        f"(dense J {out['dense'][1] / 1e6:.0f} MB); standard errors differ by {err:.1e} at most",
        flush=True,
    )
    return [
        dict(
            run=f"covariance, {L} logs, {name}",
            logs=L,
            columns=ncol,
            cold_s=out[name][2],
            warm_s=out[name][3],
            speedup=out["dense"][3] / out[name][3] if name == "ours" else None,
            dense_mb=out[name][1] / 1e6 if out[name][1] else None,
            max_rel_difference=err,
        )
        for name in ("ours", "dense")
    ]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--logs", default="1,2,4,8,16,32", help="comma-separated numbers of logs")
    parser.add_argument("--lm-logs", default="2,16", help="numbers of logs for the Levenberg-Marquardt rows")
    parser.add_argument("--cov-logs", default="16,64", help="numbers of logs for the covariance rows")
    parser.add_argument("--per-log", default="", help="a parameter fitted per log (e.g. payload.mass)")
    parser.add_argument("--repeats", type=int, default=3, help="warm runs per case (median)")
    parser.add_argument("--json", default=None, help="also write the results as JSON to this path")
    args = parser.parse_args(argv)
    env = environment()
    rows = []
    lm_runs = (
        ("ours", lm(levenberg_marquardt_module._residual_fn_lm, True)),
        ("ours, dense QR", lm(levenberg_marquardt_module._residual_fn_lm, False)),
        ("dense", lm(_dense_lm, False)),
    )
    for L in [int(s) for s in args.logs.split(",")]:
        p, x, z = problem(L, args.per_log)
        ncol = len(p.names) + len(p.y0_free) + len(p.offset_free)
        block = lambda: jax.block_until_ready(residual(p, x, z))  # noqa: E731
        timed(block)
        t_res = median_time(block, args.repeats)
        out = {}
        for name, fn in (("ours", jac_ours), ("dense", jac_dense)):
            call = lambda fn=fn: jax.block_until_ready(fn(p, x, z))  # noqa: E731
            (r, J), cold = timed(call)
            out[name] = (np.asarray(J), cold, median_time(call, args.repeats))
        J_ours, J_dense = out["ours"][0], out["dense"][0]
        err = float(np.max(np.abs(J_ours - J_dense)) / np.max(np.abs(J_dense)))
        for name in ("ours", "dense"):
            _, cold, warm = out[name]
            rows.append(
                dict(
                    run=f"jacobian, {L} logs, {name}",
                    logs=L,
                    columns=ncol,
                    cold_s=cold,
                    warm_s=warm,
                    ratio=warm / t_res,
                    speedup=out["dense"][2] / warm if name == "ours" else None,
                    max_rel_difference=err,
                )
            )
        print(
            f"  {L:3d} logs ({ncol} columns): residual {t_res:.4f} s; Jacobian ours {out['ours'][2]:.4f} s "
            f"({out['ours'][2] / t_res:.1f}x), dense {out['dense'][2]:.4f} s ({out['dense'][2] / t_res:.1f}x); "
            f"largest difference {err:.1e} of the largest entry",
            flush=True,
        )
        if str(L) in args.lm_logs.split(","):
            res = {}
            for name, solve in lm_runs:
                call = lambda solve=solve: jax.block_until_ready(solve(p, z))  # noqa: E731
                (_, steps, cost), cold = timed(call)
                res[name] = (int(steps), float(cost), cold, median_time(call, args.repeats))
            for name, _ in lm_runs:
                steps, cost, cold, warm = res[name]
                rows.append(
                    dict(
                        run=f"LM solve, {L} logs, {name}",
                        logs=L,
                        columns=ncol,
                        cold_s=cold,
                        warm_s=warm,
                        speedup=res["dense"][3] / warm if name != "dense" else None,
                        steps=steps,
                        cost=cost,
                    )
                )
            print(
                f"  {L:3d} logs: LM "
                + ", ".join(f"{n} {res[n][3]:.3f} s ({res[n][0]} steps, cost {res[n][1]:.6g})" for n, _ in lm_runs),
                flush=True,
            )
    for L in [int(s) for s in args.cov_logs.split(",") if s]:
        rows += covariance_rows(L, args.repeats, args.per_log)
    print()
    shared = f"3 shared parameters and {args.per_log} per log" if args.per_log else "4 shared parameters"
    print(f"bench_fit_many_logs: {shared}, 3 nuisances per log (1.2 s logs at 4 ms, Tsit5 1 ms)")
    publish(args.json, "fit_many_logs", env, rows, COLUMNS)
    return rows


if __name__ == "__main__":
    main()
