"""Several hybrid models (a group of sweep trials) trained together in one batched solve.

On small ODEs, per-operation dispatch, not arithmetic, dominates an epoch: a stack of ``M``
same-shaped networks costs about as much as one (the 2-state oscillator of the tests: 16 models
per epoch for twice the time of one). On larger ones arithmetic takes over from a few models on
(the 28-state cargo box: about 2.5-3x less time per model from M = 4 to 32; padding mixed widths
and depths to the largest costs part of that, see ``stack_key(architecture=True)``).
:func:`train_stack` trains ``M`` configurations
as one multiple-shooting solve over ``M·S`` rows (``S`` segments per model) and evaluates the
still-active models in one whole-trajectory solve over ``M·B`` rows (``B`` train and validation
experiments; test experiments only at the end); their derivative-matching warm starts are one
batched regression over shared forced trajectories. Yet every model remains exactly its own
trial, as :func:`physmend.ude.train.train` would run it:

* its own architecture ``(width, depth, activation)``: networks are padded to the largest width
  and depth of the stack; padded units have zero weights that never move (their gradients are
  masked, so neither AdamW nor weight decay touches them), a shallower network skips the extra
  hidden layers (``h ← h``), and each model's rows pass through its own activation;
* its own initialisation (seed) and warm start, built on its own :class:`HybridModel` exactly as
  ``train()`` builds it, then copied into the padded tensors;
* its own AdamW (learning rate, weight decay, schedule and warm-up ramp), gradient clipping
  (norm 10 per model), trainable segment starts and jointly estimated parameters;
* its own evaluations, early stopping, best checkpoint and report callback; a model that stops
  (patience, divergence, an exception raised by ``report``) leaves the stack, the others go on;
* its own :class:`TrainResult` at the end, with an ordinary :class:`HybridModel` of its own
  architecture (artifacts and reloading are unchanged).

What cannot be identical: batched matrix products (``baddbmm``) and reductions over padded
tensors round differently from ``nn.Linear`` on one model (differences ~1e-15 relative per step),
and the adaptive whole-trajectory solver picks one step size for all rows of a batched
evaluation, so checkpoint metrics agree with a solo evaluation to the solver tolerance. The final
metrics of each model come from its own solo evaluation, exactly as ``train()`` computes them, or
(``final_eval="batched"``, as sweeps use it) from one batched solve of all finished models.

The public face: :func:`train_stack`, :func:`stack_key` and :data:`SHARED_KEYS`. The modules:
``keys`` (what a stack shares), ``train`` (the epoch loop and the final evaluations), ``net`` (padded
networks), ``plan`` (reference and plan, once per problem), ``solve`` (the batched model, its losses
and step), ``evaluation`` (batched whole-trajectory checkpoints), ``members`` (each model prepared,
the shared warm start). The rules of checkpoints, patience, restarts and polishing are those of the
single-model trainer (:mod:`physmend.ude.checkpoints`); the two trainers are siblings on the same pieces.
"""

from __future__ import annotations

from physmend.ude.stack.keys import SHARED_KEYS, stack_key
from physmend.ude.stack.train import train_stack

__all__ = ["SHARED_KEYS", "stack_key", "train_stack"]
