"""The mask's rules on their own (:mod:`physmend.masking.choice`): the rival equation sets worth
retraining, the set whose retrained network is kept, and a candidate's line in the printout."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from physmend.masking.choice import SourceNetwork, best_retrained, choose_k, rivals, val_text
from physmend.ude import TrainingDiverged


def test_mask_rivals_and_the_best_retrained_set() -> None:
    """The mask stage retrains the next-ranked equation in place of the last kept one and keeps
    whichever set validates best; a diverged retraining never wins, and all diverging is an error."""
    assert rivals(["tank2.h"], ["tank2.h", "tank1.h", "pipe.q"], 1) == [["tank1.h"]]
    assert rivals(["a", "b"], ["a", "b", "c", "d", "e"], 2) == [["a", "c"], ["a", "d"]]
    assert rivals(["a"], ["a"], 3) == [] and rivals(["a"], ["a", "b"], 0) == []
    # only an unmeasured rival for a measured last kept state
    measured = {"tank2.h", "pipe.q"}
    assert rivals(["tank2.h"], ["tank2.h", "pipe.q", "tank1.h"], 1, measured) == [["tank1.h"]]
    assert rivals(["tank1.h"], ["tank1.h", "tank2.h", "tank3.h"], 1, measured) == []
    # a kept set mixing measured and hidden states: the hidden ones alone and the measured ones alone are rivals
    assert rivals(["tank2.h", "tank1.h"], ["tank2.h", "tank1.h"], 1, measured) == [["tank1.h"], ["tank2.h"]]
    assert rivals(["tank2.h", "tank1.h", "pipe.q"], ["tank2.h", "tank1.h", "pipe.q", "tank3.h"], 1, measured) == [
        ["tank1.h"], ["tank2.h", "pipe.q"], ["tank2.h", "tank1.h", "tank3.h"]]
    assert rivals(["tank2.h", "pipe.q"], ["tank2.h", "pipe.q"], 1, measured) == []
    ranked, rival = SimpleNamespace(val_rmse=0.009), SimpleNamespace(val_rmse=0.002)
    assert best_retrained([(["tank2.h"], ranked), (["tank1.h"], rival)]) == (["tank1.h"], rival)
    # the source network masked to a set competes with that set's retraining: the better one is kept
    retrained, masked = SimpleNamespace(val_rmse=0.19), SourceNetwork(0.137)
    assert best_retrained([(["central.A"], retrained), (["central.A"], masked)])[1] is masked
    boom = TrainingDiverged("loss became non-finite")
    assert best_retrained([(["tank2.h"], ranked), (["tank1.h"], boom)]) == (["tank2.h"], ranked)
    with pytest.raises(TrainingDiverged, match="non-finite"):
        best_retrained([(["tank2.h"], boom), (["tank1.h"], TrainingDiverged("other"))])
    # a smaller set within the tolerance of the best wins; outside it, the best
    both, alone = SimpleNamespace(val_rmse=0.0100), SimpleNamespace(val_rmse=0.0105)
    assert best_retrained([(["tank1.h", "tank2.h"], both), (["tank1.h"], alone)], 0.1) == (["tank1.h"], alone)
    assert best_retrained([(["tank1.h", "tank2.h"], both), (["tank1.h"], alone)], 0.01) == (["tank1.h", "tank2.h"], both)


def test_k_is_the_smallest_within_the_tolerance_of_the_full_network_or_else_of_the_best_masked_one() -> None:
    assert choose_k(1.0, [(1, 1.5), (2, 1.05), (3, 1.0)], 0.1) == 2
    assert choose_k(1.0, [(1, 3.0), (2, 2.1), (3, 2.0)], 0.1) == 2  # none near the full network: near the best masked


def test_a_candidate_line_says_its_rmse_or_why_it_has_none() -> None:
    assert val_text(SimpleNamespace(val_rmse=0.012345)) == "0.01235"
    assert val_text(SourceNetwork(0.5)) == "0.5"


@pytest.mark.parametrize("held", [True, False], ids=["test experiments", "none"])
def test_the_retrained_line_shows_the_held_out_test_rmse(held: bool) -> None:
    """The retrained network's test RMSE comes from its held-out simulation (training never saw the
    test experiments, so its own metrics have none): printed where there is one, left out where not."""
    from physmend.masking.corrections import MaskOutcome
    from physmend.masking.report import report
    from physmend.ude import TrainResult

    trained = TrainResult(val_rmse=0.1143, metrics={"val.rmse": 0.1143}, history=[], artifacts={})
    out = MaskOutcome(ranking=[("a", 0.5), ("b", 0.1)], by_k=[(1, 0.2)], full=0.1, k=1, kept=["a"], kept_in_order=["a"],
                      corrected=["a", "b"], config=None, own=False, retrained=True, tried=[(["a"], trained)],
                      winner=trained, trained=trained,
                      held_out=TrainResult(val_rmse=0.1143, metrics={"val.rmse": 0.1143, "test.rmse": 1.3999},
                                           history=[], artifacts={}) if held else trained)
    line = report(out, "run", SimpleNamespace(tolerance=0.1, retrain_epochs=3)).splitlines()[-1]
    assert line == ("Retrained with 1 output(s): validation RMSE 0.1143, test RMSE 1.4." if held
                    else "Retrained with 1 output(s): validation RMSE 0.1143.")
