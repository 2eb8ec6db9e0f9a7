"""Whole-trajectory solves of a drive-form hybrid by fixed-step RK4, kept where step doubling shows
them within the solver's tolerances.

A checkpoint evaluation simulates every model of a stack over whole records with the stiff
adaptive solver: about one Rodas step per sample (its steps end on every input knot), each a
handful of batched right-hand sides dispatched from Python — seconds per checkpoint. The models
are the drive form that training solves by RK4 (:mod:`physmend.ude.adjoint`), so the same compiled
right-hand side (:mod:`physmend.ude.rk4_steps`) can take whole records: every row steps first on
its own stops (its measured times and input kinks, where the adaptive solver's clock per row ends
its steps; a gap in a record cut into steps of the row's median interval), then with every step
halved, up to :data:`LEVELS` grids. As soon as two grids in a row agree to within
``15·(atol + rtol·|u|)`` at every point of the coarser one (RK4 being fourth order, the finer
grid's error there is about a fifteenth of the difference: within ``atol + rtol·|u|``), the answer
is the finer one with that estimate taken off on the coarser one's points (Richardson's
extrapolation), so its error is far below the tolerances, as an adaptive solver's is in practice
(an adaptive solve at ``rtol = 1e-3`` was 1.6 % off the exact validation RMSE where this was 1e-5
off, tests/stages/test_sweep.py's model).
Where none do, a grid would be too large (:data:`MAX_ELEMENTS`), or the answer leaves the
states' limits, None is returned and the caller's adaptive solve decides (and reports its error
as before). Values between grid points (another record's sample times) are the cubic Hermite
interpolant of the states and derivatives at the step's ends. Nothing here depends on the time
scale: the grids come from the records.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch

from physmend.simulate import PiecewiseLinear
from physmend.ude.compiled_solve import _loop, codes, pack
from physmend.ude.drive import network_parts, columns, drivable, physics_drive
from physmend.ude.hybrid import HybridModel
from physmend.ude import rk4_steps
from physmend.ude.activation_loops import CODES

#: solver methods with error control (rtol, atol) whose solves this may stand in for
ADAPTIVE = ("rodas3", "rodas4", "rodas4p2", "dopri5", "dopri8", "bosh3", "fehlberg2", "adaptive_heun", "tsit5")
#: grids tried: the first the stops, each next one with every step halved
LEVELS = 5
#: grid points × states of the largest grid solved here (its states and derivatives: 2 × 8 bytes each)
MAX_ELEMENTS = 2**23
#: elements of the drives held at once (a record is solved in chunks of steps within this)
CHUNK_ELEMENTS = 2**21
#: solves answered here and those left to the adaptive solver, in this process (what tests read)
STATS = {"kept": 0, "declined": 0}


@dataclass
class DriveForm:
    """The drive form of ``M`` models over ``R = M·S`` rows (model-major), as
    :func:`physmend.ude.adjoint.rk4_adjoint` takes it, with its time-dependent parts as a function:
    ``drive(times (H, R))`` gives ``d (H, R, n)`` and ``pre (H, M, S, w₀)`` at each row's times (s)."""

    A: torch.Tensor  # (R, n, n)
    drive: Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]]
    wu: torch.Tensor  # (M, r, w0)
    layers: Sequence[tuple[torch.Tensor, torch.Tensor]]
    gain: torch.Tensor  # broadcastable to (M, S, k)
    reads: torch.Tensor | None
    index: torch.Tensor | None
    activation: str | tuple[str, ...]  # one for every model, or each model's
    models: int


def hybrid_form(hybrid: HybridModel, p: torch.Tensor, inputs: PiecewiseLinear, mask: torch.Tensor | None = None
                ) -> DriveForm | None:
    """The drive form of one hybrid on the rows of ``inputs`` (``p (R, n_params)``, estimated;
    ``mask (R, k)``: each row's own output mask, as :func:`~physmend.ude.drive.drive_table`); None
    where the drive form does not apply or the network has no hidden layer."""
    if not drivable(hybrid) or not hybrid.spec.widths:
        return None
    bound = hybrid.compiled.bind(p)
    pre, wu_t, rest, gain = network_parts(hybrid, p, inputs.values[:, :1].transpose(0, 1), mask)
    layers = [(w.unsqueeze(0), b.view(1, 1, -1)) for b, w in (x for x in rest if isinstance(x, tuple))]

    def drive(times: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        xs = inputs.at_each(times)  # (H, R, n_inputs)
        return physics_drive(hybrid, p, xs)[1], network_parts(hybrid, p, xs, mask)[0].unsqueeze(1)

    return DriveForm(bound.A, drive, wu_t.unsqueeze(0), layers, gain.view(1, -1, gain.shape[-1]), *columns(hybrid),
                     hybrid.spec.activation, 1)


def applies(sim: dict, activation: str | Sequence[str], device: torch.device) -> bool:
    """Whether :func:`rk4_states` may stand in for the solve ``sim`` (an adaptive method with no
    options of its own but the clocks, on the CPU, activations the compiled loops have: one name,
    or each model's)."""
    names = [activation] if isinstance(activation, str) else activation
    return (sim["method"] in ADAPTIVE and set(sim["options"]) <= {"clocks"} and device.type == "cpu"
            and all(a in CODES for a in names))


def rk4_states(form: DriveForm, u0: torch.Tensor, t: torch.Tensor, stops: Sequence[torch.Tensor] | None,
               rtol: float, atol: float, limits: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor | None:
    """States ``(T, R, n)`` at ``t (T,)`` from ``u0 (R, n)``, each row stepping on its ``stops[r]``
    (s; None: every row on ``t``), or None where no two grids agree within ``rtol``/``atol``, or
    the answer leaves ``limits = (lo, hi)`` (each ``(n,)``) (module docstring)."""
    if t.shape[0] < 2:
        return None
    out = _states(form, u0, t, [t] * u0.shape[0] if stops is None else list(stops), rtol, atol, limits)
    STATS["kept" if out is not None else "declined"] += 1
    return out


def _states(form: DriveForm, u0: torch.Tensor, t: torch.Tensor, stops: list[torch.Tensor], rtol: float, atol: float,
            limits: tuple[torch.Tensor, torch.Tensor] | None) -> torch.Tensor | None:
    grid, real = _first_grid(stops, float(t[0]), float(t[-1]), u0.dtype)
    prev = None
    for level in range(LEVELS):
        if level:
            grid, real = _halved(grid), 2 * real
        if grid.numel() * u0.shape[-1] > MAX_ELEMENTS:  # a long record: the adaptive solve's windows
            return None
        now = _solve(form, u0, grid)
        if now is not None and prev is not None:
            change = now[0][::2] - prev[0]
            scale = atol + rtol * torch.maximum(prev[0].abs(), now[0][::2].abs())
            if bool((change.abs() <= (2**4 - 1) * scale).all()):
                inside = limits is None or bool(((now[0] >= limits[0]) & (now[0] <= limits[1])).all())
                if not inside:
                    return None
                states = now[0].clone()
                states[::2] += change / (2**4 - 1)  # Richardson's extrapolation on the coarser grid's points
                return _dense(grid, real, states, now[1], t)
        prev = now
    return None


def _first_grid(rows: Sequence[torch.Tensor], t0: float, t1: float, dtype: torch.dtype
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """Each row's grid ``(R, K+1)``: ``t0``, its stops within, ``t1``, an interval longer than the
    row's median one (a gap in a record) in equal steps no longer than that; rows with fewer steps
    end with steps of 0 at ``t1``. And each row's step count ``(R,)``."""
    grids = []
    for s in rows:
        pts = torch.unique(torch.cat([s.to(dtype)[(s > t0) & (s < t1)], torch.tensor([t0, t1], dtype=dtype)]))
        gaps = pts.diff()
        cuts = torch.ceil(gaps / gaps.median() - 1e-9).clamp_min(1).to(torch.long)
        local = torch.arange(int(cuts.sum())) - torch.repeat_interleave(cuts.cumsum(0) - cuts, cuts)
        frac = local.to(dtype) / torch.repeat_interleave(cuts, cuts).to(dtype)
        grids.append(torch.cat([torch.repeat_interleave(pts[:-1], cuts) + frac * torch.repeat_interleave(gaps, cuts),
                                pts[-1:]]))
    K = max(g.shape[0] for g in grids) - 1
    real = torch.tensor([g.shape[0] - 1 for g in grids])
    return torch.stack([torch.cat([g, g.new_full((K + 1 - g.shape[0],), t1)]) for g in grids]), real


def _halved(grid: torch.Tensor) -> torch.Tensor:
    """Every step of ``grid (R, K+1)`` cut in two: ``(R, 2K+1)``."""
    out = grid.new_empty(grid.shape[0], 2 * grid.shape[1] - 1)
    out[:, 0::2] = grid
    out[:, 1::2] = 0.5 * (grid[:, :-1] + grid[:, 1:])
    return out


def _solve(form: DriveForm, u0: torch.Tensor, grid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor] | None:
    """States and derivatives ``(K+1, R, n)`` on ``grid (R, K+1)`` (chunks of steps, the compiled
    loops), or None where they are not finite."""
    R, n = u0.shape
    K = grid.shape[1] - 1
    M = form.models
    S = R // M
    dt = u0.dtype
    W, b, dims, fixed = pack(form.wu, form.gain, [x for pair in form.layers for x in pair], form.reads, form.index,
                             M, S, n)
    L, P, k = W.shape[0], W.shape[-1], dims[-1]
    At = form.A.detach().expand(R, n, n).transpose(1, 2).contiguous()
    hs = grid.diff(dim=1).contiguous()
    half = grid.new_empty(grid.shape[0], 2 * K + 1)
    half[:, 0::2] = grid
    half[:, 1::2] = 0.5 * (grid[:, :-1] + grid[:, 1:])
    chunk = max(8, CHUNK_ELEMENTS // (2 * (form.wu.shape[-1] * R + R * n)))
    traj, slope = u0.new_empty(K + 1, R, n), u0.new_empty(K + 1, R, n)
    Vs, Z, Y, OUT = u0.new_empty(R, 4, n), u0.new_empty(L, R, 4, P), u0.new_empty(L, R, 4, P), u0.new_empty(R, 4, k)
    activations = codes(form.activation, M)
    loop = _loop(rk4_steps, "steps", R)
    u = u0.detach().contiguous()
    with torch.no_grad():
        for k0 in range(0, max(K, 1), chunk):
            k1 = min(K, k0 + chunk)
            d, pre = form.drive(half[:, 2 * k0:2 * k1 + 1].T)
            H = 2 * (k1 - k0) + 1
            loop(hs[:, k0:k1].contiguous().numpy(), u.numpy(), At.numpy(), d.detach().expand(H, R, n).contiguous().numpy(),
                 pre.detach().expand(H, M, S, pre.shape[-1]).contiguous().numpy(), *(x.numpy() for x in fixed), activations, S,
                 traj[k0:k1 + 1].numpy(), slope[k0:k1 + 1].numpy(), Vs.numpy(), Z.numpy(), Y.numpy(), OUT.numpy())
            u = traj[k1].contiguous()
    if not (bool(torch.isfinite(traj).all()) and bool(torch.isfinite(slope).all())):
        return None
    return traj, slope


def _dense(grid: torch.Tensor, real: torch.Tensor, traj: torch.Tensor, slope: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """States at ``t (T,)`` ``(T, R, n)``: the grid values where ``t`` is a grid point of the row,
    else the cubic Hermite interpolant of the step that spans it (each row's ``real`` steps only)."""
    R = grid.shape[0]
    tt = t.to(grid.dtype)[None, :].expand(R, -1).contiguous()
    a = torch.searchsorted(grid.contiguous(), tt, right=True) - 1
    a = torch.minimum(a.clamp_min(0), (real - 1)[:, None])  # (R, T)
    rows = torch.arange(R)[:, None]
    g0, g1 = grid[rows, a], grid[rows, a + 1]
    width = g1 - g0
    theta = ((tt - g0) / width)[..., None]  # (R, T, 1)
    w = width[..., None]
    u_a, u_b = traj[a, rows], traj[a + 1, rows]  # (R, T, n)
    f_a, f_b = slope[a, rows], slope[a + 1, rows]
    th2, th3 = theta * theta, theta * theta * theta
    y = ((2 * th3 - 3 * th2 + 1) * u_a + (th3 - 2 * th2 + theta) * w * f_a
         + (-2 * th3 + 3 * th2) * u_b + (th3 - th2) * w * f_b)
    return y.transpose(0, 1)


def warm_shared(dtype: torch.dtype = torch.float64, threads: int | None = None) -> None:
    """Compile the whole-trajectory loop's twin that shares rows among threads (or read it from
    numba's cache) with a solve of a few numbers; nothing for one thread. ``threads``: those the
    later solves run on (default: this process's torch threads now). A process that will solve on
    all its CPUs later does it while it would otherwise wait (``physmend discover`` while its
    sweep's other workers end their trials; the mask stage's parent while its children retrain):
    seconds once per installation (8 s measured on a fresh one, 2 cores)."""
    threads = torch.get_num_threads() if threads is None else int(threads)
    if threads < 2:
        return
    g = torch.Generator().manual_seed(0)
    A, d, pre, wu, w, b, gain = (torch.randn(*s, dtype=dtype, generator=g)
                                 for s in ((threads, 2, 2), (3, threads, 2), (3, 1, threads, 3), (1, 2, 3), (1, 3, 2),
                                           (1, 1, 2), (1, threads, 2)))
    form = DriveForm(A, lambda times: (d, pre), wu, [(w, b)], gain, None, None, "tanh", 1)
    now = torch.get_num_threads()  # the twin is picked by torch's thread count (compiled_solve._loop)
    try:
        torch.set_num_threads(threads)
        with torch.no_grad():
            _solve(form, torch.zeros(threads, 2, dtype=dtype), torch.tensor([[0.0, 0.1]] * threads, dtype=dtype))
    finally:
        torch.set_num_threads(now)

