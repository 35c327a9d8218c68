"""``overtake-layout``: several processes' recordings joined into one file with one layout.

Processes that share a recording id (``--recording-id``) open as one recording, but each
sends its own layout and the viewer shows whichever came last: a trainer knows only its own
run, a spectator only the roads. This command reads what the files hold — the runs'
curves (``training/...``), their cars (``trainer/<run>/...``), which arenas each remote run
drives (``trainer/<run>/arenas``) and the roads a spectator or server recorded
(``world/<server>/arena<k>/shape``) — and writes one ``.rrd`` with all of it and a layout
that shows it together:

- **compare**: each run's road (its first arena, as a spectator recorded it), one above the
  other, over the key plots (return, average speed, collisions, loss), every run a line in
  each;
- **training**: the plots alone; **cars**: each run's first environment (camera, LIDAR,
  Q-values, reward, actions) side by side;
- a tab per arena (its road, camera, LIDAR and plots).

The recordings' chunks are copied as they are into one recording (the layouts the processes
sent are left behind), with this layout as its default: ``rerun FILE`` opens it laid out.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from overtake.cli import Command, CommandError, Output

from .recording import APPLICATION_ID, FLUSH_TIMEOUT_S
from .training_layout import car_layout, curves_layout, key_curves_layout
from .world_view import ArenaShape, arena_layout, road_view

log = logging.getLogger("overtake.layout")


class LayoutError(CommandError, RuntimeError):
    """The recordings could not be read or joined; the message says which and why."""


@dataclass
class Contents:
    """What a set of recordings holds, as far as a layout needs it."""

    runs: list[str] = field(default_factory=list)
    shapes: list[ArenaShape] = field(default_factory=list)
    run_arenas: dict[str, tuple[str, list[int]]] = field(default_factory=dict)

    def run_shapes(self, run: str) -> list[ArenaShape]:
        """The recorded arenas run ``run`` drives (in its order)."""
        if run not in self.run_arenas:
            return []
        server, arenas = self.run_arenas[run]
        by_id = {(s.server, s.arena): s for s in self.shapes}
        return [by_id[(server, a)] for a in arenas if (server, a) in by_id]


def _first_values(chunk: Any) -> dict[str, Any]:
    """A static AnyValues chunk's columns, each column's first value (``name`` from
    ``AnyValues:name`` or ``name``)."""
    batch = chunk.to_record_batch()
    out: dict[str, Any] = {}
    for name, column in zip(batch.schema.names, batch.columns, strict=True):
        values = column.to_pylist()
        if not values or values[0] is None:
            continue
        value = values[0]
        while isinstance(value, list) and len(value) == 1:
            value = value[0]
        out[name.rsplit(":", 1)[-1]] = value
    return out


def open_reader(path: Path) -> Any:
    """An ``rr.chunk.RrdReader`` of ``path``. The server's and the spectator's recordings are
    written without a footer on purpose (overtake.viz.recording, on footers): the reader's
    warning that such a file is of a "legacy format" is not for the user of this command."""
    import warnings

    import rerun as rr

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="RRD file has no footer", category=Warning)
        return rr.chunk.RrdReader(str(path))


def read_contents(paths: Sequence[Path]) -> Contents:
    """Runs, arenas and who drives which, from the recordings' entity paths and static
    metadata."""
    contents = Contents()
    seen_shapes: set[tuple[str, int]] = set()
    for path in paths:
        try:
            chunks = open_reader(path).stream().to_chunks()
        except Exception as error:
            raise LayoutError(f"cannot read the recording {path}: {error}") from None
        for chunk in chunks:
            parts = chunk.entity_path.strip("/").split("/")
            if parts[0] == "trainer" and len(parts) >= 2 and parts[1] not in contents.runs:
                contents.runs.append(parts[1])
            if not chunk.is_static:
                continue
            if parts[0] == "trainer" and len(parts) == 3 and parts[2] == "arenas":
                values = _first_values(chunk)
                arenas = values.get("arenas")
                if arenas is not None and values.get("server") is not None:
                    arena_list = arenas if isinstance(arenas, list) else [arenas]
                    contents.run_arenas[parts[1]] = (
                        str(values["server"]),
                        [int(a) for a in arena_list],
                    )
            if parts[0] == "world" and len(parts) == 4 and parts[3] == "shape":
                try:
                    shape = ArenaShape.from_values(_first_values(chunk))
                except (KeyError, TypeError, ValueError) as error:
                    raise LayoutError(
                        f"{path}: {chunk.entity_path} is not an arena's shape (server, arena, "
                        f"lane_count, lane_width_m, lidar_range_m, camera): {error!r}"
                    ) from None
                if (shape.server, shape.arena) not in seen_shapes:
                    seen_shapes.add((shape.server, shape.arena))
                    contents.shapes.append(shape)
    return contents


def combined_blueprint(contents: Contents) -> Any:
    """The layout described in the module's docstring."""
    import rerun.blueprint as rrb

    tabs: list[Any] = []
    runs = contents.runs
    roads = [
        road_view(shapes[0], f"{run}: road (arena {shapes[0].arena}, agent 0 at 0 m)")
        for run in runs
        if (shapes := contents.run_shapes(run))
    ]
    if runs:
        tabs.append(
            rrb.Vertical(
                *roads, key_curves_layout(), row_shares=[1] * len(roads) + [2], name="compare"
            )
            if roads
            else curves_layout(runs)
        )
        if roads:
            tabs.append(curves_layout(runs))
        tabs.append(rrb.Horizontal(*(car_layout(run) for run in runs), name="cars"))
    for shape in contents.shapes:
        owner = next((r for r in runs if shape in contents.run_shapes(r)), None)
        title = f"{shape.server} arena {shape.arena}" + (f" ({owner})" if owner else "")
        tabs.append(arena_layout(shape, title))
    if not tabs:
        raise LayoutError("the recordings hold neither training runs nor roads to lay out")
    timeline = "step" if runs else "round"
    return rrb.Blueprint(
        rrb.Tabs(*tabs), rrb.TimePanel(timeline=timeline, state="collapsed"), collapse_panels=True
    )


@dataclass(frozen=True)
class LayoutConfig:
    """Join recordings of one run (a spectator's, the trainers') into one laid-out .rrd."""

    recordings: tuple[Path, ...]
    """the .rrd files to join"""
    out: Path = Path("combined.rrd")
    """the joined recording (written beside, then renamed: never half-written)"""

    def output_paths(self) -> tuple[Output, ...]:
        """What this command writes (checked before the recordings are read)."""
        return (Output("--out", self.out),)


def main(config: LayoutConfig) -> Contents:
    """Write the joined, laid-out recording; returns what it holds."""
    import rerun as rr

    missing = [str(p) for p in config.recordings if not p.is_file()]
    if missing:
        raise LayoutError(f"no such recording: {', '.join(missing)}")
    contents = read_contents(config.recordings)
    blueprint = combined_blueprint(contents)
    readers = [open_reader(p) for p in config.recordings]
    recordings = [store for reader in readers for store in reader.recordings()]
    if not recordings:
        raise LayoutError("the files hold no recording (only layouts?)")
    config.out.parent.mkdir(parents=True, exist_ok=True)
    partial = config.out.with_name(config.out.name + ".partial")
    # Only the recordings' data is copied: the layouts each process sent stay behind, so the
    # file opens with this one.
    stream = rr.RecordingStream(APPLICATION_ID, recording_id=recordings[0].recording_id)
    try:
        stream.save(str(partial), default_blueprint=blueprint)
        for reader in readers:
            for store in reader.recordings():
                stream.send_chunks(reader.stream(store=store))
        stream.flush(timeout_sec=FLUSH_TIMEOUT_S)
    finally:
        stream.disconnect()
    partial.replace(config.out)
    return contents


def _report(config: LayoutConfig, contents: Any) -> None:
    print(
        f"{config.out}: {len(contents.runs)} run(s) ({', '.join(contents.runs) or 'none'}), "
        f"{len(contents.shapes)} arena(s); open it with: rerun {config.out}"
    )


COMMAND = Command("overtake-layout", LayoutConfig, main, report=_report, prefixed=True)


if __name__ == "__main__":
    COMMAND.run()
