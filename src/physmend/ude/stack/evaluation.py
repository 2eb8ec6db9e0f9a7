"""Checkpoint and final evaluations of a stack: the models' whole trajectories simulated in one
batched adaptive solve (each model alone where the batched solve fails). A part of :class:`Stack`
(:mod:`physmend.ude.stack.solve`), which supplies the networks, estimates and right-hand sides.
"""

from __future__ import annotations

from typing import Any
import dataclasses
import math

import torch

from physmend.problem import Problem
from physmend.simulate import Batch
from physmend.ude.fixed_step import applies, rk4_states
from physmend.simulate.initial import estimate_initial
from physmend.ude.metrics import LEAVE_MARGIN, evaluate_with, guarded, metrics_of, row_stops
from physmend.ude.outcome import TrainingDiverged
from physmend.ude.reference import clocked, simulate_with, with_stops
from physmend.ude.stack.net import StackedNet, write_back_row


class StackEvaluation:
    """Whole-trajectory evaluations of the stacked models (mixed into :class:`~physmend.ude.stack.solve.Stack`)."""

    def evaluate(self, positions: list[int], sim: dict[str, Any], *, full: bool = False
                 ) -> list[tuple[dict[str, float], torch.Tensor] | BaseException]:
        """Whole-trajectory metrics of the models at ``positions`` in one batched solve (per model on failure).

        Checkpoints simulate the train and validation experiments; ``full`` every experiment
        (test ones included), as a final evaluation does, with outputs at every time of the batch
        (for figures). Checkpoint experiments recorded at different times take only their own
        steps: in one solve with a clock per row where the solver has clocks and they pay
        (:func:`~physmend.simulate.batch.own_stops`; each model then steps as if alone), otherwise
        solved apart per time grid (:func:`~physmend.ude.stack.plan.time_grid_parts`).
        """
        m = len(positions)
        problem = self.problem if full else self.checked
        batch = self.full_batch if full else self.eval_batch
        b = batch.size
        rows = torch.tensor(positions, dtype=torch.long)
        net = self.net.select(rows)
        est = None if self.est_raw is None else self.est_raw.detach()[rows]
        parts = [(list(range(b)), batch, None)] if full or clocked(sim, batch) else self.parts
        try:
            with torch.no_grad():
                if len(parts) == 1:
                    y = self._simulate(net, est, positions, batch, sim)
                else:  # (T, M, B, k) on the union of times; each experiment set only where it has times
                    y = torch.full((batch.t.shape[0], m, b, len(self.problem.compiled.output_names)), math.nan,
                                   dtype=self.dtype)
                    for exps, part, at in parts:
                        y_part = self._simulate(net, est, positions, part, sim)
                        y[at[:, None], :, torch.tensor(exps)[None, :]] = y_part.reshape(-1, m, len(exps), y.shape[-1]).movedim(1, 2)
                    y = y.reshape(y.shape[0], m * b, -1)
        except Exception:  # noqa: BLE001 - one model's failure must not end the others: solve each alone
            return [self._evaluate_alone(i, sim, problem) for i in positions]
        out: list[tuple[dict[str, float], torch.Tensor] | BaseException] = []
        for j in range(m):
            y_j = y[:, j * b:(j + 1) * b]
            try:
                out.append((metrics_of(problem, batch, y_j), y_j))
            except TrainingDiverged as exc:
                out.append(exc)
        return out

    def _simulate(self, net: StackedNet, est: torch.Tensor | None, positions: list[int], batch: Batch,
                  sim: dict[str, Any]) -> torch.Tensor:
        """Outputs ``(T, M·B, k)`` of the models at ``positions`` (networks ``net``, estimates ``est``)
        on every experiment of ``batch``, rows model-major, in one adaptive solve."""
        m, b = len(positions), batch.size
        rep = torch.arange(b).repeat(m)
        names = [f"{self.members[i].slot}:{e}" for i in positions for e in batch.ids]
        batch_m = batch.take(rep, ids=names)
        limits = self.members[0].hybrid.spec.box(LEAVE_MARGIN, self.problem.dtype)

        def outputs(rows: Batch, u0: torch.Tensor) -> torch.Tensor:
            """Rows model-major, the same experiments for every model (as every caller here builds them)."""
            p = self._parameters_for(rows.params[: rows.size // m], est, m)  # (M·R, n_params)
            names = self.problem.compiled.state_names
            # by fixed-step RK4 where that is within tolerance (it needs no drive table), else the adaptive solve
            states = self._fixed_step(net, m, p, rows, u0, sim, limits)
            if states is None:
                driven = self._drive_table(net, m, p, rows.inputs)
                if driven is None:
                    states = simulate_with(guarded(self._rhs(net, m, p), limits, rows.ids, names), rows, u0, sim)
                else:  # the same function with the input-dependent work done once per knot
                    states = simulate_with(guarded(driven[0], limits, rows.ids, names),
                                           dataclasses.replace(rows, inputs=driven[1]), u0, with_stops(sim, rows))
            return self.problem.compiled.outputs(states, rows.inputs.at(rows.t), p[None])

        # declared-unknown initial values: each model's own estimates (a failed candidate solve is
        # raised: the caller then evaluates each model alone, where failures are isolated)
        key = tuple(names)
        u0 = estimate_initial(outputs, batch_m, self.problem.compiled.state_names, isolate=False,
                              near=self.initial_estimates.get(key))
        if any(batch_m.initial_ranges):
            self.initial_estimates[key] = u0  # the next checkpoint of these models starts about them
        return outputs(batch_m, u0)  # (T, M·B, k)

    def _fixed_step(self, net: StackedNet, m: int, p: torch.Tensor, rows: Batch, u0: torch.Tensor, sim: dict[str, Any],
                    limits: tuple[torch.Tensor, torch.Tensor] | None) -> torch.Tensor | None:
        """States ``(T, m·R, n)`` of the rows by :func:`~physmend.ude.fixed_step.rk4_states` (each row
        from the stops its own clock would take), or None where it does not apply
        or does not agree within the solver's tolerances (the adaptive solve then decides)."""
        form = self._form(net, m, p, rows.inputs)
        if form is None or torch.is_grad_enabled() or not applies(sim, form.activation, u0.device):
            return None
        return rk4_states(form, u0, rows.t, row_stops(rows, sim), sim["rtol"], sim["atol"], limits)

    def _evaluate_alone(self, position: int, sim: dict[str, Any], problem: Problem
                        ) -> tuple[dict[str, float], torch.Tensor] | BaseException:
        member = self.members[position]
        self.write_back(position)
        try:
            metrics, y, _ = evaluate_with(member.hybrid, problem, sim)
        except Exception as exc:  # noqa: BLE001 - what train() would have raised for this model
            return exc
        return metrics, y

    def write_back(self, position: int) -> None:
        write_back_row(self.net, position, self.members[position].hybrid, self.est_raw)
