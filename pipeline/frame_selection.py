"""The ``--frames`` option: a frame selection ('START:STOP[:STEP]' over indices, or a comma list of
frame ids or indices) as frame indices, refusing a START:STOP written as frame ids where the ids
are numbers (parse_frames)."""

from __future__ import annotations

from pipeline.errors import ConfigError


def parse_frames(spec: str | None, frame_ids: list[str]) -> list[int] | None:
    """Frame selection: 'START:STOP[:STEP]' over indices, or a comma list of frame ids/indices."""
    if not spec:
        return None
    spec = spec.strip()
    if ":" in spec:
        try:
            parts = [int(p) if p else None for p in spec.split(":")]
            if len(parts) > 3 or (len(parts) == 3 and parts[2] == 0):
                raise ValueError
        except ValueError:
            raise ConfigError(f"--frames: cannot parse '{spec}' (use START:STOP[:STEP] with a non-zero STEP, "
                              f"or a comma list)") from None
        _refuse_ids_as_indices(spec, frame_ids)
        chosen = list(range(len(frame_ids)))[slice(*parts)]
        if not chosen:
            raise ConfigError(f"--frames {spec}: selects no frame (this dataset has {len(frame_ids)}, "
                              f"indices 0 to {len(frame_ids) - 1})")
        return chosen
    lookup = {f: i for i, f in enumerate(frame_ids)}
    like = next((f for f in frame_ids if f.isdigit()), None)  # ids that are numbers: '60' is ambiguous
    out = []
    for item in spec.split(","):
        item = item.strip()
        if item in lookup:
            out.append(lookup[item])
        elif item.isdigit() and like is not None:
            # '60' where the ids are numbers ('000060'): an id written without its zeros, or index 60?
            raise ConfigError(f"--frames: '{item}' is no frame id here (ids are numbers like '{like}') and would "
                              f"be taken as an index: give the id as the dataset writes it, or indices as "
                              f"START:STOP ('{item}:{int(item) + 1}')")
        elif item.isdigit() and int(item) < len(frame_ids):
            out.append(int(item))
        else:
            raise ConfigError(f"--frames: no frame '{item}' in this dataset ({len(frame_ids)} frames)")
    return out


def _refuse_ids_as_indices(spec: str, frame_ids: list[str]) -> None:
    """ConfigError for a START:STOP whose START or STOP is written as a frame id where the ids are
    numbers ('000100:000110' on Astyx, whose index 100 is frame 000370), when the ids would select
    other frames than the indices do. The message gives the indices of the frames the ids name."""
    if not any(f.isdigit() for f in frame_ids):
        return
    lookup = {f: i for i, f in enumerate(frame_ids)}
    start, stop = (spec.split(":") + [""])[:2]
    as_id = [p for p in (start, stop)
             if p.isdigit() and ((len(p) > 1 and p.startswith("0")) or lookup.get(p, int(p)) != int(p))]
    if not as_id:
        return
    low, high = int(start) if start else -1, int(stop) if stop else None
    named = [i for i, f in enumerate(frame_ids) if f.isdigit() and low <= int(f) and (high is None or int(f) < high)]
    if named and named == list(range(len(frame_ids)))[slice(int(start) if start else None, high)]:
        return  # the ids are the indices there ('00000:00010' on the synthetic world)
    part = next((p for p in as_id if lookup.get(p) != int(p)), as_id[0])
    index = int(part)
    shown = f"index {index} is frame {frame_ids[index]}" if index < len(frame_ids) else f"there is no index {index}"
    ids = f"ids from {start or 'the first'} up to {stop + ' (not included)' if stop else 'the last'}"
    if named and named == list(range(named[0], named[-1] + 1)):
        way = (f"the frames with {ids} are `--frames {named[0] if start else ''}:"
               f"{named[-1] + 1 if stop else ''}`")
    elif named:
        way = f"the {len(named)} frames with {ids} are not one run of indices: list their ids, comma-separated"
    else:
        way = f"no frame here has one of the {ids}"
    raise ConfigError(f"--frames {spec}: START:STOP are indices, but '{part}' is written as a frame id ({shown}): {way}")
