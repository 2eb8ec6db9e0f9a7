"""``threads: auto`` as a count: the CPUs this process may use, shared among processes side by side,
capped by ``OMP_NUM_THREADS`` where a process was told its share."""

from __future__ import annotations

import pytest

from physmend.cpus import threads, usable_cpus


def test_a_number_is_kept_and_auto_is_this_process_s_share(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    assert threads(3) == 3 and threads(1, side_by_side=8) == 1
    cpus = usable_cpus()
    assert threads("auto") == cpus
    assert threads("auto", side_by_side=cpus) == 1
    assert threads("auto", side_by_side=cpus + 5) == 1  # never 0
    assert threads("auto", side_by_side=2) == max(1, cpus // 2)


def test_auto_obeys_the_share_a_process_was_told(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert threads("auto") == 1
    assert threads(2) == 2  # a number given wins over the environment
    monkeypatch.setenv("OMP_NUM_THREADS", "1000")
    assert threads("auto") == usable_cpus()  # never more than this process may use
    monkeypatch.setenv("OMP_NUM_THREADS", "four")
    assert threads("auto") == usable_cpus()  # not a whole number: ignored


def test_loading_a_problem_sets_torch_to_the_resolved_count(monkeypatch: pytest.MonkeyPatch) -> None:
    import torch

    from physmend.config import compose
    from physmend.problem import load_problem

    before = torch.get_num_threads()
    try:
        monkeypatch.setenv("OMP_NUM_THREADS", "1")
        load_problem(compose([]))
        assert torch.get_num_threads() == 1
        load_problem(compose(["threads=2"]))
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)


def test_a_process_working_beside_others_takes_its_share_until_it_is_alone_again(monkeypatch: pytest.MonkeyPatch) -> None:
    from physmend.cpus import side_by_side

    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    cpus = usable_cpus()
    with side_by_side(cpus):
        assert threads("auto") == 1
        with side_by_side(1):
            assert threads("auto") == cpus
        assert threads("auto") == 1 and threads(2) == 2
    assert threads("auto") == cpus
