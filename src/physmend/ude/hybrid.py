"""The universal differential equation ``du/dt = f(u, x, p) + M ⊙ s ⊙ NN(z; θ)``.

``z`` are normalised network inputs (states, chosen observed variables, exogenous inputs, chosen
parameters), ``M`` selects the corrected equations and ``s`` scales each correction to the
typical size of its state's derivative, so that a freshly initialised network perturbs the
physics only slightly.

With ``units: equation`` (the default) the network's output is a term of the equation
``a_i(p)·der(x_i) = …`` in that equation's own units (a heat flow in W, a force in N, a current in
A) and is divided by ``a_i(p)``: missing physics is a missing flow or force, the same whatever the
capacity, mass or volume of the experiment, so a network need not learn ``1/a_i`` and carries over
to an experiment whose capacity training never saw. ``units: state`` corrects ``du_i/dt`` directly. Parameters declared uncertain can be estimated jointly (kept inside
their bounds by a sigmoid).
"""

from __future__ import annotations

import fnmatch
import warnings
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import torch
from torch import nn

from physmend.device import on_cpu
from physmend.exceptions import PhysmendError
from physmend.modeling.compile import CompiledModel

ACTIVATIONS: dict[str, Callable[[], nn.Module]] = {
    "tanh": nn.Tanh,
    "relu": nn.ReLU,
    "gelu": nn.GELU,
    "softplus": nn.Softplus,
    "silu": nn.SiLU,
    "sigmoid": nn.Sigmoid,
    "elu": nn.ELU,
}


class UDEConfigError(PhysmendError, ValueError):
    """A ``ude.*`` setting does not fit the model; the message names the key."""


def match_names(patterns: Sequence[str], names: Sequence[str], key: str) -> list[str]:
    """Names matching any glob pattern, in model order; a pattern matching nothing is an error."""
    out: list[str] = []
    for pat in patterns:
        hits = [n for n in names if fnmatch.fnmatchcase(n, str(pat))]
        if not hits:
            raise UDEConfigError(f"{key}: pattern {pat!r} matches no name of the model (names: {list(names)[:12]}…)")
        out += [h for h in hits if h not in out]
    return [n for n in names if n in out]


@dataclass
class HybridSpec:
    """Everything needed to rebuild a hybrid model besides its weights (stored as JSON)."""

    corrected: list[str]
    in_states: list[str]
    in_observed: list[str]
    in_inputs: list[str]
    in_parameters: list[str]
    widths: list[int]
    activation: str
    mean: list[float]
    std: list[float]
    out_scale: list[float]
    estimated: list[str] = field(default_factory=list)
    #: "equation": the network's outputs are terms of ``a_i·der(x_i) = …`` in its units (divided by
    #: ``a_i(p)``); "state": rates ``du_i/dt`` (specs stored before the choice existed)
    units: str = "state"
    #: each correction's typical initial size in state units per second (empty: ``out_scale``)
    rate_scale: list[float] = field(default_factory=list)
    #: per state, its range over the training samples of the model as written (None: the model as
    #: written holds it constant, so no scale is known and it is not bounded); empty: not recorded
    state_low: list[float | None] = field(default_factory=list)
    state_high: list[float | None] = field(default_factory=list)

    def box(self, margin: float, dtype: torch.dtype = torch.float64) -> tuple[torch.Tensor, torch.Tensor] | None:
        """``(lo, hi)``, each ``(n_states,)``: the training range widened by ``margin`` ranges on
        either side (``∓inf`` for an unbounded state); None when no range was recorded."""
        if not self.state_low:
            return None
        lo = torch.tensor([-torch.inf if v is None else v for v in self.state_low], dtype=dtype)
        hi = torch.tensor([torch.inf if v is None else v for v in self.state_high], dtype=dtype)
        width = hi - lo
        return lo - margin * width, hi + margin * width

    @property
    def n_inputs(self) -> int:
        return len(self.in_states) + len(self.in_observed) + len(self.in_inputs) + len(self.in_parameters)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @property
    def input_names(self) -> list[str]:
        return self.in_states + self.in_observed + self.in_inputs + self.in_parameters


def der_coefficients(problem_or_model: Any, names: Sequence[str]) -> Callable[[torch.Tensor], torch.Tensor]:
    """``coef(p) -> (..., k)``: ``a_i(p)`` of each equation ``a_i·der(x_i) = …`` of ``names`` for
    parameters ``p (..., n_params)`` (a model, or anything with a ``.model``)."""
    from physmend.modeling.compile import lambdify_torch

    model = getattr(problem_or_model, "model", problem_or_model)
    fn = lambdify_torch([v.symbol for v in model.parameters], [model.der_coefficient.get(n, 1) for n in names],
                        "der coefficients")

    def coef(p: torch.Tensor) -> torch.Tensor:
        vals = fn(*p.unbind(-1))
        return torch.stack([torch.as_tensor(v, dtype=p.dtype, device=p.device).expand(p.shape[:-1]) for v in vals], -1)

    return coef


def make_mlp(n_in: int, widths: Sequence[int], n_out: int, activation: str) -> nn.Sequential:
    if activation not in ACTIVATIONS:
        raise UDEConfigError(f"ude.activation must be one of {sorted(ACTIVATIONS)}, but got {activation!r}")
    layers: list[nn.Module] = []
    last = n_in
    for w in widths:
        layers += [nn.Linear(last, int(w)), ACTIVATIONS[activation]()]
        last = int(w)
    with warnings.catch_warnings():  # n_out == 0 (no correction) warns about an empty init
        warnings.simplefilter("ignore", UserWarning)
        layers.append(nn.Linear(last, n_out))
    return nn.Sequential(*layers)


class HybridModel(nn.Module):
    """Physics plus a neural correction of selected equations (see module docstring).

    Shapes: states ``u (..., B, n_states)``, inputs ``x (..., B, n_inputs)``, parameters
    ``p (B, n_params)``; corrections ``(..., B, n_corrected)`` in state units per second.
    """

    def __init__(self, compiled: CompiledModel, spec: HybridSpec, dtype: torch.dtype = torch.float64) -> None:
        super().__init__()
        self.compiled = compiled
        self.spec = spec
        #: experiment IDs -> this model's last estimates of their unknown initial values ``(B, n)``
        #: (:func:`physmend.ude.metrics.hybrid_states` starts the next search about them)
        self.initial_estimates: dict[tuple[str, ...], torch.Tensor] = {}
        names = compiled.state_names
        self.corrected_idx = [names.index(n) for n in spec.corrected]
        self.state_idx = [names.index(n) for n in spec.in_states]
        self.observed_idx = [compiled.observed_names.index(n) for n in spec.in_observed]
        self.input_idx = [compiled.input_names.index(n) for n in spec.in_inputs]
        self.param_idx = [compiled.parameter_names.index(n) for n in spec.in_parameters]
        self._all_states = self.state_idx == list(range(len(names)))
        self._all_inputs = self.input_idx == list(range(len(compiled.input_names)))
        self.register_buffer("mean", torch.tensor(spec.mean, dtype=dtype))
        self.register_buffer("std", torch.tensor(spec.std, dtype=dtype))
        self.register_buffer("out_scale", torch.tensor(spec.out_scale, dtype=dtype))
        self.register_buffer("rate_scale", torch.tensor(spec.rate_scale or spec.out_scale, dtype=dtype), persistent=False)
        #: ``a_i(p)`` of the corrected equations (``units: equation``), else None
        self.coefficients = der_coefficients(compiled.model, spec.corrected) if spec.units == "equation" and spec.corrected else None
        # 1 keeps a correction, 0 masks it (output masking evaluates top-k subsets this way)
        self.register_buffer("out_mask", torch.ones(len(spec.corrected), dtype=dtype), persistent=False)
        with on_cpu():  # the same initial weights for a seed on every device (physmend.device)
            net = make_mlp(spec.n_inputs, spec.widths, len(spec.corrected), spec.activation).to(dtype)
            with torch.no_grad():  # start with small corrections
                last = net[-1]
                last.weight.mul_(0.1)
                last.bias.zero_()
        self.net = net.to(torch.get_default_device())
        params = {v.name: v for v in compiled.model.parameters}
        self.est_idx = [compiled.parameter_names.index(n) for n in spec.estimated]
        lo = [params[n].bounds[0] for n in spec.estimated]  # type: ignore[index]
        hi = [params[n].bounds[1] for n in spec.estimated]  # type: ignore[index]
        self.register_buffer("est_lo", torch.tensor(lo, dtype=dtype))
        self.register_buffer("est_hi", torch.tensor(hi, dtype=dtype))
        start = torch.tensor([params[n].value for n in spec.estimated], dtype=dtype)
        self.register_buffer("est_nominal", start.clone(), persistent=False)
        frac = ((start - self.est_lo) / (self.est_hi - self.est_lo)).clamp(1e-4, 1 - 1e-4) if spec.estimated else start
        self.est_raw = nn.Parameter(torch.logit(frac) if spec.estimated else torch.zeros(0, dtype=dtype))

    # -- parameters -----------------------------------------------------------------------------
    def parameters_for(self, p: torch.Tensor) -> torch.Tensor:
        """``p (B, n_params)`` with the jointly estimated parameters replaced by their estimates."""
        if not self.est_idx:
            return p
        values = self.est_lo + (self.est_hi - self.est_lo) * torch.sigmoid(self.est_raw)
        p = p.clone()
        p[:, self.est_idx] = values.to(p.dtype)
        return p

    def estimates(self) -> dict[str, float]:
        if not self.est_idx:
            return {}
        values = self.est_lo + (self.est_hi - self.est_lo) * torch.sigmoid(self.est_raw)
        return dict(zip(self.spec.estimated, values.detach().tolist()))

    # -- the network ----------------------------------------------------------------------------
    def features(self, u: torch.Tensor, x: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
        """Raw (unnormalised) network inputs ``(..., B, n_features)`` in physical units."""
        # every state (or input) in model order is the tensor itself: no gather (one op less per evaluation)
        parts = [u if self._all_states else u[..., self.state_idx]]
        lead = u.shape[:-1]
        if self.observed_idx:
            parts.append(self.compiled.observed(u, x, p)[..., self.observed_idx])
        if self.input_idx:
            xs = x if self._all_inputs else x[..., self.input_idx]
            parts.append(xs if xs.shape[:-1] == lead else xs.expand(*lead, len(self.input_idx)))
        if self.param_idx:
            parts.append(p[..., self.param_idx].expand(*lead, len(self.param_idx)))
        return torch.cat(parts, dim=-1)

    def corrections(self, u: torch.Tensor, x: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
        """Network corrections ``(..., B, n_corrected)`` in state units per second."""
        return self.corrector(p)(u, x)

    def corrector(self, p: torch.Tensor) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor]:
        """:meth:`corrections` for fixed parameters ``p (B, n_params)``: what depends on ``p`` and
        the output mask only (``a_i(p)``, the output gains) is computed once here, not at every
        evaluation of a solve — the same numbers either way."""
        gain = self.out_scale * self.out_mask
        coef = self.equation_coefficients(p) if self.coefficients is not None else None

        def corr(u: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
            out = self.net((self.features(u, x, p) - self.mean) / self.std) * gain
            return out if coef is None else out / coef

        return corr

    def equation_coefficients(self, p: torch.Tensor) -> torch.Tensor:
        """``a_i(p)`` of the corrected equations ``(..., k)`` for ``p (..., n_params)``, with every
        jointly estimated parameter at its declared value: the network's term is converted to a rate
        by the capacity as written, so an estimate and the network cannot trade one scale for the
        other (a heat capacity doubled with the correction doubled)."""
        assert self.coefficients is not None
        if self.est_idx:
            p = p.clone()
            p[..., self.est_idx] = self.est_nominal.to(p.dtype)
        return self.coefficients(p)

    def corrections_of_z(self, z: torch.Tensor) -> torch.Tensor:
        """Corrections from normalised features ``z (..., n_features)`` (for sensitivities), in the
        network's own units (the equation's with ``units: equation``: not divided by ``a_i``)."""
        return self.net(z) * (self.out_scale * self.out_mask)

    def keep_only(self, names: list[str]) -> None:
        """Mask every correction except those of the states ``names``."""
        self.out_mask = torch.tensor([1.0 if n in names else 0.0 for n in self.spec.corrected], dtype=self.out_mask.dtype,
                                     device=self.out_mask.device)

    def rhs(self, p: torch.Tensor, rows: torch.Tensor | None = None) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor]:
        """``f(u, x) -> du/dt`` of the hybrid for parameters ``p (B, n_params)`` (already estimated);
        with ``rows (S,)``, element ``s`` has ``p[rows[s]]`` (:meth:`CompiledModel.bind`)."""
        physics = self.compiled.bind(p, rows)
        idx = self.corrected_idx
        n = len(self.compiled.state_names)
        if not idx:  # nothing corrected: the physics alone (e.g. re-fitting a formula's constants)
            return physics
        corrections = self.corrector(p if rows is None else p[rows])  # a_i(p) and the gains once per solve
        if len(idx) == n and idx == list(range(n)):
            return lambda u, x: physics(u, x) + corrections(u, x)

        index = torch.tensor(idx, dtype=torch.long, device=p.device)

        def f(u: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
            corr = corrections(u, x)
            du = physics(u, x)
            if du.shape[:-1] != corr.shape[:-1]:
                lead = torch.broadcast_shapes(du.shape[:-1], corr.shape[:-1])
                du, corr = du.expand(*lead, n), corr.expand(*lead, corr.shape[-1])
            return du.index_add(-1, index, corr)

        return f
