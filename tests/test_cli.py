"""The command line: a stage's run ID, ``--config-dir`` and overrides in any order."""

from __future__ import annotations

import pytest

from physmend.cli import _parser, parse

RUN = "29156737b31f4c87b70c53ba09954c78"


@pytest.mark.parametrize("argv", [
    ["symbolic", RUN, "--config-dir", "conf", "model=m", "data=d"],
    ["symbolic", "--config-dir", "conf", "model=m", "data=d", RUN],
    ["symbolic", "--config-dir", "conf", RUN, "model=m", "data=d"],
    ["symbolic", "model=m", RUN, "--config-dir", "conf", "data=d"],
])
def test_run_id_options_and_overrides_in_any_order(argv: list[str]) -> None:
    args = parse(_parser(), argv)
    assert (args.run_id, args.config_dir, args.overrides) == (RUN, "conf", ["model=m", "data=d"])


@pytest.mark.parametrize("argv", [
    ["mask", "~data.time_unit", RUN, "model=m"],
    ["mask", RUN, "~data.time_unit", "model=m"],
    ["mask", "model=m", "~data.time_unit", RUN],
])
def test_hydras_deletion_is_an_override_not_a_run_id(argv: list[str]) -> None:
    args = parse(_parser(), argv)
    assert args.run_id == RUN and sorted(args.overrides) == ["model=m", "~data.time_unit"]


def test_a_stray_word_or_option_is_one_line_and_exit_2(capsys: pytest.CaptureFixture[str]) -> None:
    for argv, said in ((["symbolic", RUN, "other"], "overrides must look like key=value (or ~key to delete one), but got ['other']"),
                       (["diagnose", RUN], "overrides must look like key=value"),
                       (["symbolic", RUN, "--bogus", "x=1"], "unrecognized arguments: --bogus")):
        with pytest.raises(SystemExit) as exc:
            parse(_parser(), argv)
        assert exc.value.code == 2
        assert said in capsys.readouterr().err


def test_ui_on_a_tracking_server_prints_where_to_look(capsys: pytest.CaptureFixture[str]) -> None:
    """A tracking server is its own UI: ``physmend ui`` says where to open it (no password) and starts nothing."""
    from physmend.cli import main

    assert main(["ui", "tracking.uri=http://me:s3cret@127.0.0.1:9"]) == 0
    out = capsys.readouterr().out
    assert "open http://me:***@127.0.0.1:9" in out and "s3cret" not in out
