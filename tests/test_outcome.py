"""How runs end: the highest exit code wins; a run that fused nothing or lost too much fails."""

from dm2.cli.outcome import (
    EXIT_DAMAGED_INPUT,
    EXIT_MISSED,
    EXIT_OK,
    damaged_input_sentence,
    drop_lines,
    exit_code,
    run_verdict,
)


def test_the_highest_code_wins():
    assert exit_code() == EXIT_OK
    assert exit_code(EXIT_MISSED, EXIT_DAMAGED_INPUT, EXIT_OK) == EXIT_DAMAGED_INPUT


def test_verdicts_count_messages_not_points():
    ok = run_verdict(profiles_fused=10, messages_in=1000, max_lost_share=0.25,
                     dropped={"nan_points": 5000, "late_message": 200})
    assert ok == (EXIT_OK, None)
    code, text = run_verdict(profiles_fused=10, messages_in=1000, max_lost_share=0.25,
                             dropped={"late_message": 200, "implausible_stamp": 60})
    assert code == EXIT_MISSED and "26%" in text and "260 of 1,000" in text
    code, text = run_verdict(profiles_fused=0, messages_in=50, max_lost_share=0.25,
                             dropped={})
    assert code == EXIT_MISSED and "fused no profile" in text


def test_one_line_per_drop_reason_largest_first():
    assert drop_lines({"late_message": 3, "nan_points": 40, "pose_gap": 0}) == [
        "dropped 40 points: nan_points", "dropped 3 messages: late_message"]


def test_profiles_that_saw_nothing_are_counted_not_announced():
    dropped = {"empty_profile": 143, "late_message": 2}
    assert drop_lines(dropped) == ["dropped 2 messages: late_message"]
    # they still count towards the lost share, and a failed run names them
    code, text = run_verdict(profiles_fused=10, messages_in=400, max_lost_share=0.25,
                             dropped=dropped)
    assert code == EXIT_MISSED and "145 of 400" in text
    assert "143 of them profiles that saw nothing in range" in text
    assert run_verdict(profiles_fused=10, messages_in=4000, max_lost_share=0.25,
                       dropped=dropped) == (EXIT_OK, None)


def test_damaged_input_is_one_sentence():
    assert damaged_input_sentence({"complete": True}) is None
    text = damaged_input_sentence({"file": "cut.mcap", "complete": False,
                                   "last_stamp_s": 12.5, "bytes_skipped": 2048})
    assert text == ("cut.mcap is truncated or damaged: it was read up to 12.500 s, and 2,048 "
                    "bytes after that could not be read.")
