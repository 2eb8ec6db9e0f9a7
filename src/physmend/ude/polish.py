"""Polishing a trained hybrid with L-BFGS after Adam (``train.polish``).

The multiple-shooting loss is deterministic and full-batch: every epoch is one batched solve of
every segment. Adam's steps are about ``lr`` long whatever the curvature, so a network that must
move far (a correction of an unmeasured state that no warm start could set) is still descending
when its schedule ends. A quasi-Newton method on the same loss (L-BFGS with a strong-Wolfe line
search, the usual second phase of universal-differential-equation training) takes the rest of the
way in a fraction of the solves. The whole-trajectory checkpoints keep judging: the best
checkpoint by validation RMSE is still the one kept, so polishing can only help the chosen model.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
import math

import torch


#: remembered curvature pairs of L-BFGS
HISTORY = 20

#: the training fit, in multiples of the fit that sensor noise alone leaves (``shooting.noise_fit``),
#: at or below which L-BFGS is not run: the loss it would minimise has nothing left but noise
AT_NOISE = 2.0

#: ``objective() -> (loss, fit)``: the loss L-BFGS minimises (its sum, for several models at once)
#: and the fit part, each a tensor ``()`` or ``(M,)``
Objective = Callable[[], tuple[torch.Tensor, torch.Tensor]]


def worth_polishing(fit: float, noise: float) -> bool:
    """Whether a network whose best checkpoint left the training fit term ``fit`` is worth polishing,
    given ``noise``, the fit term of sensor noise alone (both in the loss's units: mean squared error
    over each output's spread). L-BFGS minimises the training loss; at the noise there is nothing
    left for it to take (the cargo-box network's fit sat at 0.76× the noise's: its polish cost 40%
    more time and never improved validation). Unknown values (NaN) polish."""
    return not (math.isfinite(fit) and math.isfinite(noise) and noise > 0 and fit <= AT_NOISE * noise)


def fit_at(history: Sequence[dict[str, float]], val_rmse: float) -> float:
    """The fit term logged at the checkpoint whose validation RMSE is ``val_rmse`` (NaN: none)."""
    return next((float(r.get("fit_loss", math.nan)) for r in history if r.get("val.rmse") == val_rmse), math.nan)


class Polisher:
    """L-BFGS (strong-Wolfe line search) over ``params``, run a few iterations at a time so that the
    caller can checkpoint in between; its curvature memory lasts as long as the object."""

    def __init__(self, params: Sequence[torch.Tensor]) -> None:
        self.params = [p for p in params if p.numel()]
        self.opt = (torch.optim.LBFGS(self.params, lr=1.0, history_size=HISTORY, line_search_fn="strong_wolfe",
                                      tolerance_grad=1e-12, tolerance_change=1e-14) if self.params else None)
        self.iterations = 0
        self.stalled = False  # L-BFGS stopped early: no more progress to make

    def run(self, objective: Objective, n: int) -> bool:
        """At most ``n`` more iterations on ``objective``; False (parameters restored to where the
        call began) when a step left the finite range."""
        if self.opt is None or n <= 0 or self.stalled:
            self.stalled = True
            return True
        saved = [p.detach().clone() for p in self.params]
        opt = self.opt

        def closure() -> torch.Tensor:
            opt.zero_grad(set_to_none=True)
            loss = objective()[0].sum()
            if not torch.isfinite(loss):  # the line search backs off from a step out of the finite range
                return loss.detach().new_tensor(float("inf"))
            loss.backward()
            return loss

        opt.param_groups[0]["max_iter"] = n
        loss = opt.step(closure)
        before = self.iterations
        self.iterations = int(opt.state[self.params[0]].get("n_iter", before + n))
        self.stalled = self.iterations < before + n
        finite = loss is not None and bool(torch.isfinite(loss.detach())) and all(bool(torch.isfinite(p).all()) for p in self.params)
        if not finite:
            with torch.no_grad():
                for p, s in zip(self.params, saved):
                    p.copy_(s)
        return finite


def polish_lbfgs(objective: Objective, params: Sequence[torch.Tensor], iterations: int, every: int,
                 checkpoint: Callable[[int, torch.Tensor, torch.Tensor], bool],
                 regroup: Callable[[], Sequence[torch.Tensor] | None] | None = None) -> int:
    """Minimise ``objective`` over ``params`` for at most ``iterations`` L-BFGS iterations, calling
    ``checkpoint(k, loss, fit)`` (k: iterations so far; the current loss and fit) after every
    ``every`` of them; it returns True to stop. ``regroup()``, after a checkpoint that does not stop,
    returns the parameters of a new L-BFGS when the set of models changed (some of a stack stopped),
    else None. Ends at a step out of the finite range (parameters of the last checkpoint restored)
    or when L-BFGS makes no more progress. Returns the iterations done."""
    polisher = Polisher(params)
    done = 0
    while done < iterations and polisher.opt is not None:
        step = min(max(1, every), iterations - done)
        if not polisher.run(objective, step):
            break
        done += step
        with torch.no_grad():
            loss, fit = objective()
        if checkpoint(done, loss, fit) or polisher.stalled:
            break
        fresh = None if regroup is None else regroup()
        if fresh is not None:
            polisher = Polisher(fresh)
    return done
