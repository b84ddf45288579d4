"""A run hands its Ctrl-C critical section to every device link, and takes it back at the end.

The transports no longer read a global: the run's `Interrupts` reaches the drivers through the
station (`Station.guard_exchanges`), so this checks the wiring end to end, through the real
drivers on the emulators, with the factory `labcal run --station --emulate` uses.
"""

from __future__ import annotations

from contextlib import ExitStack

from conftest import quiet_console
from emulators import no_leaks, private_file  # noqa: F401 - no_leaks is a fixture

from labcal.bench.setup import hardware_station, prepare
from labcal.config.plans import load_plan
from labcal.config.settings import SequencerSettings
from labcal.config.station import load_station
from labcal.run.events import EventBus
from labcal.run.interrupts import Interrupts
from labcal.run.operator import AutoOperator
from labcal.run.runner import calibrate
from labcal.store.journal import Journal


class LinkWatcher:
    """Notes, at every point, the critical section each link holds (a "point" subscriber)."""

    def __init__(self, links: list) -> None:
        self.links = links
        self.seen: list[list] = []

    def __call__(self, event) -> None:
        self.seen.append([link.critical for link in self.links])


def test_every_link_holds_the_runs_critical_section_during_the_run_and_none_after(tmp_path, no_leaks):  # noqa: F811
    config, _ = load_station(private_file("az-modbus-tcp", tmp_path))
    plan, plan_text = load_plan("one-mount-16")
    with ExitStack() as stack:
        setup, bench = hardware_station(config, "test station", stack, emulate=True)
        links = list(bench._links.values())
        prepare(bench, setup.station, say=lambda text: None)  # as `labcal run` does: home, enable, configure
        assert links and all(link.critical is None for link in links)  # no run yet
        watcher = LinkWatcher(links)
        events = EventBus()
        events.subscribe(watcher, kinds=("point",))
        run_dir = tmp_path / "run"
        run_dir.mkdir()
        with Journal(tmp_path / "j.sqlite") as journal:
            calibrate(plan, plan_text, setup.station, setup.text, AutoOperator(quiet_console()),
                      SequencerSettings(settle=setup.settle), run_dir, journal, events)
        assert len(watcher.seen) == 16
        holders = {id(getattr(c, "__self__", None)) for point in watcher.seen for c in point}
        owners = [getattr(c, "__self__", None) for point in watcher.seen for c in point]
        assert all(isinstance(o, Interrupts) for o in owners) and len(holders) == 1  # one run, one handler
        assert all(link.critical is None for link in links)  # handed back when the run ended
