"""Why a stage's output is not current: what it was made with against what this command gives.

Every output records what it was made with (:meth:`pipeline.runner.Pipeline.record`): the values
of its stage's configuration keys, the version of the stage's code, the fingerprints of the
outputs it read, and where they apply the first stage's data (root and frames) and a dataset
stage's other inputs (the nets train.nets_from took). A frame stage keeps the record in its
group's attributes, a dataset stage in ``_stage.json``. Outputs made before 2026-12-07 recorded
only the configuration values and upstream fingerprints of frame stages; what they lack is not
compared.

:func:`explain` compares a recorded and a current record and says, in words, what differs, and
which ``--set`` options would give this command the recorded settings back.
"""

from __future__ import annotations

import shlex
from dataclasses import dataclass
from typing import Any

from pipeline.config import ADDED_KEYS, READER_KEYS

MISSING = object()
"""A configuration key the recorded output does not hold (added to the stage since)."""


@dataclass(frozen=True)
class Staleness:
    """Why an output is not current. ``reasons``: phrases ('made with synth.count=disnet (this
    command: blend)'); ``sets``: 'key=value' texts that give this command the settings the output
    was made with; ``settings_only``: whether settings are all that differs, as far as the output
    records (those ``sets``, and those of the stale upstream stages it names, make it current)."""

    reasons: tuple[str, ...]
    sets: tuple[str, ...] = ()
    settings_only: bool = False

    @property
    def text(self) -> str:
        return "; ".join(self.reasons)


def sets_to_restore(whys: list[Staleness]) -> tuple[list[str], bool]:
    """The ``--set`` options ('key=value', each once, in order) that give a command the settings
    the outputs ``whys`` describe were made with, and whether, as far as they record, those options
    are all that differs. Where train.nets_from is among them, the radar settings that come with
    the nets (transfer.RADAR_SETTINGS) are left out."""
    from pipeline.transfer import RADAR_SETTINGS

    sets = {s: None for why in whys for s in why.sets}
    if any(s.startswith("train.nets_from=") for s in sets):
        sets = {s: None for s in sets if s.split("=", 1)[0] not in RADAR_SETTINGS}
    return list(sets), all(why.settings_only for why in whys) and bool(sets)


def set_text(value: Any) -> str:
    """``value`` (a JSON value of a configuration key) as ``--set key=VALUE`` reads it back."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (list, tuple)):
        return ",".join(set_text(v) for v in value)
    return str(value)


def options_text(sets: list[str] | tuple[str, ...]) -> str:
    """'--set key=value ...' for ``sets`` ('key=value' texts), quoted for the shell."""
    return " ".join(f"--set {shlex.quote(s)}" for s in sets)


def setting_differences(recorded: dict[str, Any], current: dict[str, Any], reader: str) -> list[tuple[str, Any, Any]]:
    """(key, recorded value, current value) for the keys of ``current`` (key -> JSON value) whose
    recorded value differs; keys the record lacks (ADDED_KEYS at their old value excepted) and keys
    another reader uses only (READER_KEYS: in no fingerprint under this one) are left out."""
    out = []
    for key, now in current.items():
        if key in READER_KEYS and READER_KEYS[key] != reader:
            continue
        old = recorded.get(key, ADDED_KEYS.get(key, MISSING))
        if old is not MISSING and _normal(old) != _normal(now):
            out.append((key, old, now))
    return out


def _normal(value: Any) -> Any:
    """A JSON value compared as read back from a record (tuples are lists there)."""
    return [_normal(v) for v in value] if isinstance(value, (list, tuple)) else value


def _nets_name(extra: str) -> str:
    """The dataset named by train.nets_from in a train stage's extra fingerprint ('' for its own nets)."""
    return extra.split(":", 1)[0].split(">", 1)[0] if extra else ""


def explain(recorded: dict[str, Any], current: dict[str, Any], reader: str,
            stale_upstream: frozenset[str] | set[str] = frozenset()) -> Staleness:
    """Why an output whose ``recorded`` attributes (its fingerprint among them) do not match this
    command's ``current`` record (:meth:`pipeline.runner.Pipeline.record`) is not current.
    ``reader``: the dataset's reader (dataset.reader); ``stale_upstream``: the upstream stages not
    current under this command either (each says why in its own right)."""
    if recorded.get("fingerprint") == "stale":
        return Staleness(("marked stale: a stage before it was recomputed after it was made",))
    reasons: list[str] = []
    sets: list[str] = []
    settings_only = True
    diffs = setting_differences(recorded.get("config") or {}, current["config"], reader)
    if diffs:
        reasons.append("made with " + ", ".join(f"{k}={set_text(old)} (this command: {set_text(new)})"
                                                for k, old, new in diffs))
        sets += [f"{k}={set_text(old)}" for k, old, _ in diffs]
    if "config" not in recorded:  # its own settings are not known
        settings_only = False
    if "extra" in recorded and recorded["extra"] != current.get("extra", ""):
        old, new = _nets_name(recorded["extra"]), _nets_name(current.get("extra", ""))
        if old == new:
            reasons.append(f"the nets of '{old}' were trained again since it was made")
            settings_only = False
        elif old:
            reasons.append(f"made with the nets of '{old}' (train.nets_from={old}; this command: "
                           f"{f'those of {new!r}' if new else 'its own'})")
            sets.append(f"train.nets_from={old}")
        else:
            reasons.append(f"made with its own nets (this command: train.nets_from={new})")
            settings_only = False
    if "version" in recorded and recorded["version"] != current["version"]:
        reasons.append(f"made by another version of the stage's code ({recorded['version']}, now {current['version']})")
        settings_only = False
    if "data_root" in current and recorded.get("data_root") and recorded["data_root"] != current["data_root"]:
        reasons.append(f"made from the data at {recorded['data_root']}")
        settings_only = False
    if "frames_digest" in recorded and recorded["frames_digest"] != current.get("frames_digest"):
        reasons.append("made from another list of frames than the data root gives now")
        settings_only = False
    if "upstream" in recorded:
        changed = [u for u, fp in current["upstream"].items() if recorded["upstream"].get(u, fp) != fp]
    else:  # not recorded: an upstream output that is not current was, most likely, what it was made from
        changed = [u for u in current["upstream"] if u in stale_upstream]
    if [u for u in changed if u in stale_upstream]:
        reasons.append(f"made from another output of {', '.join(u for u in changed if u in stale_upstream)}")
    if [u for u in changed if u not in stale_upstream]:  # recomputed since: no setting brings the old one back
        reasons.append(f"made from an earlier output of {', '.join(u for u in changed if u not in stale_upstream)}, "
                       f"recomputed since")
        settings_only = False
    if not reasons:
        unrecorded = "version" not in recorded
        reasons.append("made with other settings or code than this command's" +
                       (" (which is not recorded: the output was made before outputs recorded it)" if unrecorded
                        else ""))
        settings_only = False
    return Staleness(tuple(reasons), tuple(sets), settings_only)
