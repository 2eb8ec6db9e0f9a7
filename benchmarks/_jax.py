"""(c) The peer: the same multiple-shooting UDE in JAX + diffrax, written as a JAX user would.

The same problem as physmend's trainer, piece by piece:

* **physics**: the compiled model's own affine split ``du/dt = A_s u + B_s x + c_s`` for each
  segment ``s`` (its experiment's parameters as declared; a model with non-affine rows is refused
  with a clear error), outputs ``y = C_s u + D_s x + e_s`` exported by probing and checked against
  the compiled model at states and inputs of the data;
* **network**: physmend's shape, activation, input normalisation, output scale and equation units
  (``÷ a_i(p)``), and its initial weights (copied from ``HybridModel`` built with the same seed);
* **data and segments**: physmend's training plan (``plan_shooting``: segments, step, inputs at
  half steps, observation indices), segment starts from the model as written with measured states
  at their records (trainable offsets, first segments pinned), the same loss (output misfit scaled
  by each output's spread + continuity penalty ``train.continuity_weight``);
* **solver and optimiser**: classical RK4 (a diffrax ``AbstractERK`` with the classical tableau)
  at physmend's step, ``jax.vmap`` over segments, one ``jax.jit`` of loss, gradient and update;
  optax AdamW with ``train.lr`` and ``train.weight_decay``, gradient clipping at norm 10 as physmend;
  float64 as physmend.

Every ``eval_every`` epochs the weights are loaded into physmend's ``HybridModel`` and physmend's
whole-trajectory ``evaluate`` decides, the stopping rule of the other methods (evaluation time is
reported apart). Not in the peer: physmend's warm start, learning-rate schedule, state box, L-BFGS
polish and joint estimation of uncertain parameters (held at their declared values).

JAX is a benchmark dependency only (``pip install .[bench]``). XLA gets as many CPU threads as torch
does for the other methods (``cfg.threads`` resolved, set before JAX is imported: one thread, or XLA's
own threading where that is every CPU).
"""

from __future__ import annotations

import os
import time
from typing import Any, ClassVar

import numpy as np

from _common import Target, TimeCapReached
from _flops import epoch_flops, rhs_flops


class NotAffine(ValueError):
    """The model's right-hand side or outputs are not affine in states and inputs."""


def xla_flags(threads: int) -> str:
    """``XLA_FLAGS`` holding XLA's CPU work to ``threads`` threads (1: no Eigen thread pool)."""
    flags = os.environ.get("XLA_FLAGS", "")
    if threads == 1:
        flags += " --xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
    return flags.strip()


def affine_form(fn: Any, u: Any, x: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(A (S, r, n), B (S, r, m), c (S, r))`` with ``fn(u, x) = A u + B x + c`` (the outputs) for ``u (S, n)``,
    ``x (S, m)`` (one row per segment); raises :class:`NotAffine` when ``fn`` differs from it at
    ``(u, x)`` (and at its double) by more than 1e-8 relative."""
    import torch

    S, n = u.shape
    m = x.shape[1]
    zu, zx = torch.zeros_like(u), torch.zeros_like(x)
    with torch.no_grad():
        c = fn(zu, zx)
        cols_u = [fn(zu + torch.nn.functional.one_hot(torch.tensor(j), n).to(u.dtype), zx) - c for j in range(n)]
        cols_x = [fn(zu, zx + torch.nn.functional.one_hot(torch.tensor(j), m).to(x.dtype)) - c for j in range(m)]
        A = torch.stack(cols_u, -1)
        B = torch.stack(cols_x, -1) if m else torch.zeros(S, c.shape[-1], 0, dtype=u.dtype)
        for scale in (1.0, 2.0):
            uu, xx = u * scale, x * scale
            want = fn(uu, xx)
            got = (A @ uu[..., None])[..., 0] + (B @ xx[..., None])[..., 0] + c
            err = float(((got - want).abs() / (want.abs() + 1.0)).max())
            if not err <= 1e-8:
                raise NotAffine(f"the model is not affine in its states and inputs (relative misfit {err:.3g} of "
                                "the exported A·u + B·x + c): the JAX peer exports only affine models")
    return A.numpy(), B.numpy(), c.numpy()


def rk4_solver() -> Any:
    """Classical fourth-order Runge–Kutta as a diffrax explicit RK solver (fixed steps only)."""
    import diffrax

    classical = diffrax.ButcherTableau(
        a_lower=(np.array([0.5]), np.array([0.0, 0.5]), np.array([0.0, 0.0, 1.0])),
        b_sol=np.array([1 / 6, 1 / 3, 1 / 3, 1 / 6]),
        b_error=np.array([1 / 6, 1 / 3 - 1, 1 / 3, 1 / 6]),  # against the midpoint rule (unused: fixed steps)
        c=np.array([0.5, 0.5, 1.0]),
    )

    class RK4(diffrax.AbstractERK):
        tableau: ClassVar[Any] = classical
        interpolation_cls: ClassVar[Any] = diffrax.ThirdOrderHermitePolynomialInterpolation.from_k

        def order(self, terms: Any) -> int:
            return 4

    return RK4()


def _activation(name: str) -> Any:
    """The JAX function of physmend's ``ude.activation`` ``name`` (torch's defaults)."""
    import jax

    if name == "gelu":
        return lambda v: jax.nn.gelu(v, approximate=False)  # torch's nn.GELU default: the exact erf form
    if name == "tanh":
        return jax.numpy.tanh
    if name in ("relu", "softplus", "silu", "sigmoid", "elu"):
        return getattr(jax.nn, name)
    raise ValueError(f"ude.activation {name!r} has no JAX counterpart in the peer")


def setup(cfg: Any, problem: Any, seed: int) -> dict[str, Any]:
    """Everything the peer needs, from physmend's own pieces (torch, untimed by the peer's epochs)."""
    import torch

    from physmend.modeling.compile import BoundRhs
    from physmend.ude.hybrid import HybridModel
    from physmend.ude.reference import train_mask, reference
    from physmend.ude.shooting import initial_segments, output_spread, pinned_starts, plan_shooting
    from physmend.ude.spec import build_spec
    from physmend.ude.timescale import resolve_times

    torch.manual_seed(seed)
    ref = reference(problem, cfg)
    cfg = resolve_times(cfg, problem, ref)
    spec = build_spec(cfg, problem, ref)
    if spec.in_observed:
        raise ValueError("the JAX peer takes states, inputs and parameters as network inputs, not observed variables")
    hybrid = HybridModel(problem.compiled, spec, problem.dtype)
    plan = plan_shooting(problem, ref.batch, cfg)
    seg0 = initial_segments(problem, ref, plan)
    pinned, lo, hi = pinned_starts(ref.batch, plan, problem.compiled.state_names)
    p = ref.batch.params[plan.exp_index]  # (S, P) as declared
    cm = problem.compiled
    physics = cm.bind(p)
    if not isinstance(physics, BoundRhs) or physics.split.rest is not None:
        raise NotAffine("the model is not affine in its states and inputs: the JAX peer exports only affine models")
    x0 = plan.x_half[0]
    A, B, c = (v.detach().numpy() for v in (physics.A, physics.B, physics.c))  # the compiled model's own split
    C, D, e = affine_form(lambda u, x: cm.outputs(u[None], x[None], p[None])[0], seg0, x0)
    coef = (hybrid.equation_coefficients(p) if hybrid.coefficients is not None
            else torch.ones(p.shape[0], len(spec.corrected), dtype=p.dtype))
    mask = train_mask(problem, ref.batch)
    state_scale = ref.states[mask].std(0).clamp_min(1e-3)
    has_next = plan.next_of >= 0
    layers = [m for m in hybrid.net if isinstance(m, torch.nn.Linear)]
    return {
        "cfg": cfg, "spec": spec, "hybrid": hybrid, "plan": plan,
        "A": A, "B": B, "c": c, "C": C, "D": D, "e": e,
        "coef": coef.numpy(), "p_in": p[:, hybrid.param_idx].numpy(),
        "state_idx": np.array(hybrid.state_idx, dtype=np.int64), "input_idx": np.array(hybrid.input_idx, dtype=np.int64),
        "corrected_idx": np.array(hybrid.corrected_idx, dtype=np.int64),
        "mean": hybrid.mean.numpy(), "std": hybrid.std.numpy(), "out_scale": hybrid.out_scale.numpy(),
        "x_half": plan.x_half.permute(1, 0, 2).contiguous().numpy(),  # (S, 2K+1, m)
        "seg0": seg0.numpy(), "fixed_first": ref.batch.u0[plan.exp_index].numpy(), "pinned": pinned.numpy(),
        "lo": lo.numpy(), "hi": hi.numpy(), "state_scale": state_scale.numpy(),
        "out_std": output_spread(ref.batch.obs[mask]).numpy(),
        "obs": tuple(v.numpy() for v in (plan.obs_s, plan.obs_k, plan.obs_w, plan.obs_j, plan.obs_y)),
        "src": np.nonzero(has_next.numpy())[0], "dst": plan.next_of[has_next].numpy(),
        "params_seg": p,
        "weights": [(l.weight.detach().numpy().T.copy(), l.bias.detach().numpy().copy()) for l in layers],
        "activation": spec.activation,
        "lr": float(cfg.train.lr), "weight_decay": float(cfg.train.weight_decay),
        "continuity": float(cfg.train.continuity_weight),
    }


def build_step(s: dict[str, Any]) -> tuple[Any, Any, Any, Any]:
    """``(params, opt_state, step, segments)``: the jitted ``step(params, opt_state) -> (params,
    opt_state, loss)`` and the jitted ``segments(params) -> (S, K+1, n)`` states of every segment."""
    import diffrax
    import jax
    import jax.numpy as jnp
    import optax

    plan = s["plan"]
    K, dt = int(plan.steps), float(plan.dt)
    act = _activation(s["activation"])
    j = {k: jnp.asarray(s[k]) for k in ("A", "B", "c", "C", "D", "e", "coef", "p_in", "mean", "std", "out_scale",
                                         "x_half", "seg0", "fixed_first", "lo", "hi", "state_scale", "out_std")}
    pinned = jnp.asarray(s["pinned"])
    obs_s, obs_k, obs_w, obs_j, obs_y = (jnp.asarray(v) for v in s["obs"])
    src, dst = jnp.asarray(s["src"]), jnp.asarray(s["dst"])
    state_idx, input_idx, corr_idx = (jnp.asarray(s[k]) for k in ("state_idx", "input_idx", "corrected_idx"))
    half_ts = jnp.arange(2 * K + 1) * (dt / 2)
    solver = rk4_solver()

    def net(w: Any, z: Any) -> Any:
        for W, b in w[:-1]:
            z = act(z @ W + b)
        W, b = w[-1]
        return z @ W + b

    def vector_field(t: Any, u: Any, args: Any) -> Any:
        w, A, B, c, coef, p_in, xs = args
        x = diffrax.LinearInterpolation(half_ts, xs).evaluate(t)
        z = (jnp.concatenate([u[state_idx], x[input_idx], p_in]) - j["mean"]) / j["std"]
        corr = net(w, z) * j["out_scale"] / coef
        return (A @ u + B @ x + c).at[corr_idx].add(corr)

    def solve(w: Any, u0: Any, A: Any, B: Any, c: Any, coef: Any, p_in: Any, xs: Any) -> Any:
        sol = diffrax.diffeqsolve(diffrax.ODETerm(vector_field), solver, t0=0.0, t1=K * dt, dt0=dt, y0=u0,
                                  args=(w, A, B, c, coef, p_in, xs), saveat=diffrax.SaveAt(t0=True, steps=True),
                                  stepsize_controller=diffrax.ConstantStepSize(), max_steps=K)
        return sol.ys  # (K+1, n)

    def trajectories(params: Any) -> tuple[Any, Any]:
        """Segment starts ``(S, n)`` and every segment's states ``(S, K+1, n)``."""
        w, free = params
        u0 = jnp.where(pinned, j["fixed_first"], jnp.clip(j["seg0"] + free * j["state_scale"], j["lo"], j["hi"]))
        return u0, jax.vmap(solve, in_axes=(None, 0, 0, 0, 0, 0, 0, 0))(
            w, u0, j["A"], j["B"], j["c"], j["coef"], j["p_in"], j["x_half"])

    def loss_fn(params: Any) -> Any:
        u0, traj = trajectories(params)
        x_grid = j["x_half"][:, 0::2]  # (S, K+1, m)
        y = (jnp.einsum("skn,stn->stk", j["C"], traj) + jnp.einsum("skm,stm->stk", j["D"], x_grid)
             + j["e"][:, None, :])  # (S, K+1, outputs)
        ya, yb = y[obs_s, obs_k, obs_j], y[obs_s, obs_k + 1, obs_j]
        fit = jnp.mean((((ya + obs_w * (yb - ya)) - obs_y) / j["out_std"][obs_j]) ** 2)
        if src.shape[0] == 0:
            return fit
        gap = (traj[src, -1] - u0[dst]) / j["state_scale"]
        return fit + s["continuity"] * jnp.mean(gap ** 2)

    opt = optax.multi_transform(
        {"net": optax.chain(optax.clip_by_global_norm(10.0), optax.adamw(s["lr"], weight_decay=s["weight_decay"])),
         "free": optax.adam(s["lr"])},
        ("net", "free"))
    params = ([(jnp.asarray(W), jnp.asarray(b)) for W, b in s["weights"]], jnp.zeros_like(j["seg0"]))
    opt_state = opt.init(params)

    @jax.jit
    def step(params: Any, opt_state: Any) -> Any:
        loss, grads = jax.value_and_grad(loss_fn)(params)
        updates, opt_state = opt.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, loss

    return params, opt_state, step, jax.jit(lambda params: trajectories(params)[1])


def load_weights(hybrid: Any, w: Any) -> None:
    """The peer's network weights into physmend's ``HybridModel`` (for physmend's evaluation)."""
    import torch

    layers = [m for m in hybrid.net if isinstance(m, torch.nn.Linear)]
    with torch.no_grad():
        for layer, (W, b) in zip(layers, w):
            layer.weight.copy_(torch.from_numpy(np.array(W).T.copy()))
            layer.bias.copy_(torch.from_numpy(np.array(b).copy()))


def check_same(s: dict[str, Any], params: Any, trajectories: Any) -> float:
    """Largest difference (in units of each state's spread) between the peer's segment trajectories
    and physmend's ``rk4_segments`` from the same starts and weights: both solve the same problem."""
    import torch

    from physmend.ude.shooting import rk4_segments

    hybrid, plan = s["hybrid"], s["plan"]
    load_weights(hybrid, params[0])
    u0 = torch.from_numpy(np.where(s["pinned"], s["fixed_first"], s["seg0"]))
    with torch.no_grad():
        ours = rk4_segments(hybrid.rhs(hybrid.parameters_for(s["params_seg"])), u0, plan).permute(1, 0, 2).numpy()
    theirs = np.asarray(trajectories(params))
    return float(np.max(np.abs(ours - theirs) / s["state_scale"]))


def run(cfg: Any, problem: Any, target: Target, *, cap_s: float, eval_every: int, seed: int) -> dict[str, Any]:
    """Train until the target or the cap; wall times (s) count from before the reference simulation."""
    import jax

    jax.config.update("jax_enable_x64", True)
    from physmend.ude.metrics import checkpoint_problem, evaluate

    start = time.perf_counter()
    s = setup(cfg, problem, seed)
    params, opt_state, step, trajectories = build_step(s)
    t_check = time.perf_counter()
    same = check_same(s, params, trajectories)
    if not same <= 1e-6:
        raise AssertionError(f"the JAX peer's segments differ from physmend's by {same:.3g} state spreads: not the same problem")
    start += time.perf_counter() - t_check  # the self-check is not the peer's work
    hybrid, checked = s["hybrid"], checkpoint_problem(problem)
    t_compile = time.perf_counter()
    params, opt_state, loss = step(params, opt_state)  # epoch 1, compiled on the way
    loss.block_until_ready()
    compile_s = time.perf_counter() - t_compile
    history: list[dict[str, float]] = []
    train_s = eval_s = 0.0
    epoch, status = 1, "capped"
    try:
        while True:
            if epoch % eval_every == 0:
                t1 = time.perf_counter()
                load_weights(hybrid, params[0])
                val = evaluate(hybrid, checked, s["cfg"])["val.rmse"]
                eval_s += time.perf_counter() - t1
                history.append({"epoch": epoch, "wall_s": time.perf_counter() - start, "val.rmse": val, "loss": float(loss)})
                if target.met(val):
                    status = "reached"
                    break
            if not np.isfinite(float(loss)):
                status = f"failed: non-finite loss at epoch {epoch}"
                break
            if time.perf_counter() - start > cap_s:
                raise TimeCapReached
            t0 = time.perf_counter()
            params, opt_state, loss = step(params, opt_state)
            loss.block_until_ready()
            train_s += time.perf_counter() - t0
            epoch += 1
    except TimeCapReached:
        pass
    wall = time.perf_counter() - start
    spec, plan = s["spec"], s["plan"]
    per_row = rhs_flops(spec, len(problem.compiled.state_names), len(problem.compiled.input_names))
    rows = 4.0 * plan.steps * plan.exp_index.shape[0]
    timed = max(epoch - 1, 1)  # epochs after the compiling first one
    return {
        "status": status,
        "wall_s": wall,
        "epochs": epoch,
        "evaluations": len(history),
        "compile_s": compile_s,
        "train_s_per_epoch": train_s / timed if epoch > 1 else float("nan"),
        "eval_s": eval_s / len(history) if history else float("nan"),
        "eval_total_s": eval_s,
        "s_per_epoch": wall / epoch,
        "rows_per_epoch": rows,
        "rows_source": "analytic (RK4: 4 x steps per segment x segments)",
        "rhs_flops": per_row,
        "flops_per_epoch": epoch_flops(rows, per_row["total"]),
        "final_val_rmse": history[-1]["val.rmse"] if history else float("nan"),
        "estimated_held_at_declared": list(spec.estimated),
        "max_difference_from_physmend_segments": same,
        "history": history,
        "jax": jax.__version__,
    }
