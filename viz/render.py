"""``overtake-render``: a recording's layout drawn to PNG by Rerun's own viewer, headless.

It starts the viewer binary from the rerun-sdk wheel with ``--headless`` (it draws with Mesa's
software Vulkan where there is no GPU; on a machine without a display it runs under
``xvfb-run``), opens the recordings, and saves one screenshot per tab asked for: the pictures
show what a user opening the files would see, not what the logged values say. The viewer is
stopped by its PID when done.

Needs, on Debian or Ubuntu: ``apt-get install xvfb mesa-vulkan-drivers`` (headless machines).
"""

from __future__ import annotations

import contextlib
import fnmatch
import logging
import os
import re
import shutil
import signal
import socket
import subprocess
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from overtake.cli import Command, CommandError, Output

from .recording import viewer_binary

log = logging.getLogger("overtake.render")

VIEWER_START_TIMEOUT_S = 60.0
# After a file opens (or a tab is chosen) the viewer loads and draws asynchronously, and the
# control API says nothing about when it is done: what the screenshot waits for is that
# screenshots taken this far apart have stopped changing (settled_screenshot).
SETTLE_INTERVAL_S = 1.0
SETTLE_SAME = 3
# The viewer greets with notifications ("software rasterizer detected", the adapter, the port)
# drawn over the right of the window; they fade after a few seconds. By default no screenshot
# is taken before the viewer has run this long.
NOTIFICATIONS_S = 12.0
SETTLE_TIMEOUT_S = 60.0


class RenderError(CommandError, RuntimeError):
    """The viewer could not be started or could not draw; the message says why."""


@dataclass(frozen=True)
class RenderConfig:
    """Draw Rerun recordings to PNG with Rerun's own viewer, headless."""

    recordings: tuple[Path, ...]
    """.rrd (and .rbl) files opened together, as `rerun FILE...` would"""
    out: Path = Path("render.png")
    """the PNG; with --tabs, one per tab: <stem>-<tab>.png beside it"""
    tabs: tuple[str, ...] = ()
    """tabs of the layout to draw, by their titles or shell patterns of them ("demo arena *"):
    every tab a pattern matches, each to <stem>-<its title>.png (default: the layout as it
    opens)"""
    views: tuple[str, ...] = ()
    """single views to draw, by their titles or patterns (after the tabs): every view a pattern
    matches, each to <stem>-<its title>.png"""
    timeline_time: int | None = None
    """move the time cursor to this point of the layout's timeline (default: the end)"""
    width: int = 1600
    """window width in pixels"""
    height: int = 1000
    """window height in pixels"""
    notifications_s: float = NOTIFICATIONS_S
    """seconds the viewer runs before the first picture: its greeting notifications, drawn
    over the right of the window, have faded by then (0: the first picture is taken once it
    holds still, notifications or not)"""
    extra_args: tuple[str, ...] = field(default_factory=tuple)
    """more arguments for the viewer"""

    def output_paths(self) -> tuple[Output, ...]:
        """What this command writes (checked before the viewer starts)."""
        return (Output("--out", self.out),)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextlib.contextmanager
def headless_viewer(
    width: int,
    height: int,
    notifications_s: float = NOTIFICATIONS_S,
    extra_args: tuple[str, ...] = (),
) -> Iterator[tuple[Any, float]]:
    """A headless Rerun viewer, started with ``extra_args`` besides its own: a
    :class:`rerun.experimental.ViewerClient` on it, and the monotonic time before which no
    picture is taken: ``notifications_s`` after it started, while its greeting notifications
    may still cover the window."""
    import rerun as rr

    port = _free_port()
    command = [
        viewer_binary(),
        "--headless",
        "--hide-welcome-screen",
        "--window-size",
        f"{width}x{height}",
        "--port",
        str(port),
        *extra_args,
    ]
    if not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY"):
        xvfb = shutil.which("xvfb-run")
        if xvfb is None:
            raise RenderError(
                "no display, and xvfb-run is not installed: install it (Debian/Ubuntu: "
                "apt-get install xvfb mesa-vulkan-drivers) or run with a DISPLAY"
            )
        command = [xvfb, "-a", *command]
    output = tempfile.TemporaryFile()  # noqa: SIM115 - lives as long as the viewer
    # The viewer's and xvfb-run's temporary folders (rerun-data-*, xvfb-run.*) in one of ours:
    # ended by a signal they leave them behind, one each per picture.
    scratch = tempfile.mkdtemp(prefix="overtake-viewer-")
    viewer = subprocess.Popen(
        command,
        stdin=subprocess.DEVNULL,
        stdout=output,
        stderr=subprocess.STDOUT,
        start_new_session=True,
        env={**os.environ, "TMPDIR": scratch},
    )

    def said() -> str:
        output.seek(0)
        return output.read().decode(errors="replace").strip()[-800:]

    started = time.monotonic()
    try:
        deadline = started + VIEWER_START_TIMEOUT_S
        client = None
        while client is None:
            if viewer.poll() is not None:
                raise RenderError(f"the viewer exited with code {viewer.returncode}: {said()}")
            if time.monotonic() > deadline:
                raise RenderError(
                    f"the viewer did not answer within {VIEWER_START_TIMEOUT_S:.0f} s: {said()}"
                )
            try:
                client = rr.experimental.ViewerClient.connect(
                    f"rerun+http://127.0.0.1:{port}/proxy"
                )
                client.get_state()
            except Exception:
                client = None
                time.sleep(0.2)  # polling a port: there is nothing to wait on
        yield client, started + notifications_s
    finally:
        # xvfb-run starts Xvfb and the viewer in our new session: end the whole group.
        with contextlib.suppress(ProcessLookupError):
            os.killpg(viewer.pid, signal.SIGTERM)
        try:
            viewer.wait(timeout=10)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(viewer.pid, signal.SIGKILL)
            viewer.wait()
        output.close()
        shutil.rmtree(scratch, ignore_errors=True)


def settled_screenshot(
    client: Any, path: Path, view_id: str | None = None, not_before: float = 0.0
) -> None:
    """Save a screenshot (of the window, or of one view) once it has stopped changing: the
    same picture SETTLE_SAME times in a row, SETTLE_INTERVAL_S apart (a view still loading or
    moving to its bounds can hold still for one interval)."""
    quiet = not_before - time.monotonic()
    if quiet > 0:
        time.sleep(quiet)  # the greeting notifications fade on a timer of the viewer's
    deadline = time.monotonic() + SETTLE_TIMEOUT_S
    current = client.take_screenshot(view_id)
    same = 1
    while same < SETTLE_SAME and time.monotonic() < deadline:
        time.sleep(SETTLE_INTERVAL_S)  # the viewer draws on its own; there is no event to await
        previous, current = current, client.take_screenshot(view_id)
        same = same + 1 if current == previous else 1
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(current)


def _tabs_containers(blueprint: dict[str, Any]) -> list[tuple[str, dict[str, Any]]]:
    return [
        (path, parts["ContainerBlueprint"])
        for path, parts in blueprint.items()
        if parts.get("ContainerBlueprint", {}).get("container_kind") == "Tabs"
    ]


def loaded_blueprint(client: Any, tabs: bool = True) -> Any:
    """The active recording's layout once the viewer has read it (it loads asynchronously):
    one with titled tabs, or with ``tabs=False`` one with views."""
    deadline = time.monotonic() + SETTLE_TIMEOUT_S
    while True:
        with contextlib.suppress(Exception):
            found = client.get_blueprint()
            if not tabs and any("ViewBlueprint" in parts for parts in found.blueprint.values()):
                return found
            if any(
                _title(found.blueprint, child)
                for _, container in _tabs_containers(found.blueprint)
                for child in container.get("contents", [])
            ):
                return found
        if time.monotonic() > deadline:
            what = "tabs" if tabs else "views"
            raise RenderError(
                f"the viewer showed no layout with {what} within {SETTLE_TIMEOUT_S} s"
            )
        time.sleep(SETTLE_INTERVAL_S)  # loading happens in the viewer; nothing to wait on


def tab_titles(client: Any, pattern: str) -> list[str]:
    """The titles of the layout's tabs that ``pattern`` (a title or a shell pattern) names, in
    the layout's order; RenderError naming the tabs where none matches."""
    blueprint = loaded_blueprint(client).blueprint
    titles = [
        _title(blueprint, child)
        for _, tabs in _tabs_containers(blueprint)
        for child in tabs.get("contents", [])
    ]
    matching = [title for title in titles if fnmatch.fnmatchcase(title, pattern)]
    if not matching:
        raise RenderError(f"the layout has no tab titled {pattern!r}; its tabs: {titles}")
    return matching


def choose_tab(client: Any, title: str) -> None:
    """Make the tab titled ``title`` the active one in the recording's layout."""
    found = loaded_blueprint(client)
    blueprint = found.blueprint
    for _, tabs in _tabs_containers(blueprint):
        for child in tabs.get("contents", []):
            if _title(blueprint, child) == title:
                tabs["active_tab"] = child
                client.set_blueprint(blueprint, store_id=found.store_id)
                return
    raise RenderError(f"the layout has no tab titled {title!r}")


def _title(blueprint: dict[str, Any], child: str) -> str:
    parts = blueprint.get(child, {})
    record = parts.get("ContainerBlueprint") or parts.get("ViewBlueprint") or {}
    return str(record.get("display_name", ""))


def main(config: RenderConfig) -> list[Path]:
    """Draw the recordings; returns the PNGs written."""
    missing = [str(p) for p in config.recordings if not p.is_file()]
    if missing:
        raise RenderError(f"no such recording: {', '.join(missing)}")
    written: list[Path] = []
    # The viewer takes a while to start and to settle (its greeting fades first): say so.
    log.info(
        "drawing with Rerun's viewer, headless (about %.0f s before the first picture)",
        config.notifications_s + SETTLE_SAME * SETTLE_INTERVAL_S,
    )
    viewer = headless_viewer(config.width, config.height, config.notifications_s, config.extra_args)
    with viewer as (client, quiet_from):
        client.open([str(p.resolve()) for p in config.recordings])
        if config.timeline_time is not None:
            client.set_time(sequence=config.timeline_time, play_state="paused")
        else:
            # A file opens playing from its start; the default is its end.
            client.set_time(play_state="following")
        if not config.tabs and not config.views:
            settled_screenshot(client, config.out, not_before=quiet_from)
            return [config.out]
        # A pattern draws every tab it names, each to a file named by its own title.
        for title in (t for pattern in config.tabs for t in tab_titles(client, pattern)):
            choose_tab(client, title)
            path = _beside(config.out, title)
            settled_screenshot(client, path, not_before=quiet_from)
            written.append(path)
        if config.views:
            loaded_blueprint(client, tabs=False)
            views = {view.name: view.view_id for view in client.get_state().views}
            for title in config.views:
                found = [name for name in views if fnmatch.fnmatchcase(name, title)]
                if not found:
                    raise RenderError(
                        f"the layout has no view titled {title!r}; its views: {sorted(views)}"
                    )
                for name in found:
                    path = _beside(config.out, name)
                    settled_screenshot(client, path, view_id=views[name], not_before=quiet_from)
                    written.append(path)
    return written


def _beside(out: Path, title: str) -> Path:
    """``out`` with ``title`` (made file-name safe) added to its stem."""
    slug = re.sub(r"[^a-z0-9]+", "-", title.lower()).strip("-")
    return out.with_name(f"{out.stem}-{slug}{out.suffix}")


def _report(_config: RenderConfig, paths: list[Path]) -> None:
    for path in paths:
        print(path)


COMMAND = Command(
    "overtake-render", RenderConfig, main, report=_report, prefixed=True, log_format="%(message)s"
)


if __name__ == "__main__":
    COMMAND.run()
