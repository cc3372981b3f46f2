"""How a run ends: one exit-code table for every command, drop lines, the damaged-input sentence.

=====  =============================================================================
code   meaning
=====  =============================================================================
0      success
1      an expectation or target was missed (a scenario's ``[expect]``, a suite's
       targets, a run that fused nothing or lost more than ``max_lost_share`` of its
       input)
2      bad input, or a refusal (configuration, files, an output folder dm2 may not
       write)
3      completed on damaged input (a truncated or corrupt recording), unless
       ``--allow-truncated``
4      the system refused to write: out of disk space, a read-only file system or no
       permission (one line names the path; no partial file is left unlisted)
=====  =============================================================================

Where several apply, the highest wins (:func:`exit_code`).
"""

from __future__ import annotations

EXIT_OK, EXIT_MISSED, EXIT_BAD_INPUT, EXIT_DAMAGED_INPUT, EXIT_CANNOT_WRITE = 0, 1, 2, 3, 4

# drop reasons that count points or connections, not messages: no share of the input
NOT_MESSAGES = frozenset({"nan_points", "out_of_range", "reference_pose_gap",
                          "connection_limit", "idle_connection"})


# drop reasons that are not announced as drops: a profile that saw nothing in range is normal
# (the fan off the part at turns, past its edges); report.json counts them, and they still count
# towards the lost share (a blinded sensor must not pass), which then names them
QUIET_REASONS = frozenset({"empty_profile"})


def exit_code(*codes: int) -> int:
    """The exit code of a run several outcomes apply to: the highest."""
    return max((int(c) for c in codes), default=EXIT_OK)


def counts_messages(reason: str) -> bool:
    """Whether a drop reason counts messages (not points, gaps or connections)."""
    return reason not in NOT_MESSAGES and not reason.endswith("points")


def lost_messages(dropped: dict) -> int:
    return int(sum(v for k, v in dropped.items() if counts_messages(k)))


def drop_lines(dropped: dict) -> list[str]:
    """One line per drop reason with its count, largest first (not the QUIET_REASONS)."""
    unit = {"nan_points": "points", "out_of_range": "points", "reference_pose_gap": "gaps",
            "connection_limit": "connections", "idle_connection": "connections"}
    return [f"dropped {n:,} {unit.get(k, 'messages' if counts_messages(k) else 'points')}: {k}"
            for k, n in sorted(dropped.items(), key=lambda kv: (-kv[1], kv[0]))
            if n and k not in QUIET_REASONS]


def run_verdict(*, profiles_fused: int, dropped: dict, messages_in: int,
                max_lost_share: float) -> tuple[int, str | None]:
    """``(code, sentence)`` for a monitored run: EXIT_MISSED with a plain summary when it
    fused nothing or lost more than ``max_lost_share`` of the messages it received."""
    lost = lost_messages(dropped)
    received = max(int(messages_in), 1)
    share = lost / received
    quiet = sum(int(dropped.get(k, 0)) for k in QUIET_REASONS)
    why = (f"see the reasons above; {quiet:,} of them profiles that saw nothing in range"
           if quiet else "see the reasons above")
    if profiles_fused == 0:
        return EXIT_MISSED, (f"the run fused no profile: {messages_in:,} messages received, "
                             f"{lost:,} dropped ({why}); nothing was measured")
    if share > max_lost_share:
        return EXIT_MISSED, (f"the run lost {share:.0%} of its input ({lost:,} of {received:,} "
                             f"messages, {why}; at most {max_lost_share:.0%} allowed by "
                             "monitor.gates.max_lost_share): its results are not trustworthy")
    return EXIT_OK, None


def stream_verdicts(streams: dict, max_lost_share: float) -> tuple[int, list[str]]:
    """``(code, lines)`` for a live run's streams (``{"robot"|"S1"|...: {"received", "kept",
    "lost_share"}}``): EXIT_MISSED with one line per stream, each profiler and the robot, that
    lost more than ``max_lost_share`` of what it sent (a blinded sensor fails the run even
    when the others' messages outnumber its loss)."""
    lines = []
    for name, s in sorted(streams.items()):
        if s["received"] and s["lost_share"] > max_lost_share:
            what = "robot states" if name == "robot" else "profiles"
            lines.append(f"stream {name} lost {s['lost_share']:.0%} of its {what} "
                         f"({s['received'] - s['kept']:,} of {s['received']:,}; at most "
                         f"{max_lost_share:.0%} allowed by monitor.gates.max_lost_share): "
                         "its results are not trustworthy")
    return (EXIT_MISSED if lines else EXIT_OK), lines


def duplicate_source_lines(streams: dict) -> list[str]:
    """One line per second source that sent frames for a sensor with a live stream."""
    return [f"a second source ({d['source']}) sent {d['frames_dropped']:,} frames for "
            f"{d['sensor']}, which streams from {streams['sources'].get(d['sensor'])}: "
            "dropped (duplicate_source), the first stream kept"
            for d in streams.get("duplicate_sources", [])]


def damaged_input_sentence(info: dict) -> str | None:
    """One plain sentence when the input was truncated, damaged or recovered from a damaged
    file (its ``input`` section), else None."""
    if info.get("complete", True):
        return None
    name = info.get("file", "the input")
    parts = []
    if info.get("error") is not None or info.get("bytes_skipped"):
        upto = info.get("last_stamp_s")
        where = f"up to {upto:.3f} s" if upto is not None else "before its first message"
        at, why = info.get("stopped_at_byte"), info.get("reason")
        rest = (f"bytes from byte {at:,} on could not be read ({why})" if at is not None
                else "bytes after that could not be read")
        parts.append(f"{name} is truncated or damaged: it was read {where}, and "
                     f"{info.get('bytes_skipped', 0):,} {rest}.")
    rec = info.get("recovered")
    if rec is not None:
        trust = "" if rec.get("intact", True) else " (its recovery record fails its CRC)"
        size = str(rec.get("original_bytes", "?"))
        size = f"{int(size):,}" if size.isdigit() else size
        parts.append(f"{name} was recovered by `dm2 recover` from {rec.get('original_file')} "
                     f"({size} bytes): {rec.get('note')}{trust}.")
    if info.get("summary_damaged"):
        parts.append(f"{name}: its summary (the index) fails its CRC; it was read record by "
                     "record instead.")
    if info.get("bad_attachments"):
        parts.append(f"{name}: attachments that fail their CRC were left out: "
                     + ", ".join(info["bad_attachments"]) + ".")
    return " ".join(parts) or f"{name} is damaged."
