"""pyserial URL handler for `sim://`: an in-process fake Flock of Birds on the machine's clock (or one given to
`simulation_for`), no pty.

`serial.serial_for_url("sim://NAME?birds=16&motion=walk&seed=3&rate=144&baud=115200")`; several
ports may share one flock by NAME (`&port=k`, one line per bird). An open port's `simulation` (and its
`performer`) is the live FakeFlock and pose source, to inject line faults or a sensor slip while a client
is connected; `get_simulation(NAME)` finds a named one. The package's __init__ registers the scheme.
"""

from __future__ import annotations

import itertools
import threading
import urllib.parse
from dataclasses import dataclass, field

from serial.serialutil import PortNotOpenError, SerialBase, SerialException, Timeout, to_bytes

from flockcal.clock import SYSTEM, Clock
from flockcal.simulator.fake_tracker import FakeFlock, LineFaults
from flockcal.simulator.performer import Performer

URL_HELP = ("sim://[NAME]?birds=N&motion=walk&seed=S&noise=tracker|none&model=human&sta_mm=MM&rate=HZ&baud=B&ert=0|1"
            "&scale=36|72&port=K&quaternion=fob|conjugate&rts=reset|standby|ignore")


@dataclass
class Simulation(LineFaults):
    """One simulated flock that sim:// ports attach to."""

    name: str
    flock: FakeFlock
    source: Performer
    params: dict
    named: bool
    open_ports: dict[int, int] = field(default_factory=dict)  # port → open handles
    generation: dict[int, int] = field(default_factory=dict)  # bumped by disconnect()

    def disconnect(self, port: int | None = None) -> None:
        """Unplug: open handles on the port fail with SerialException and cannot reopen until
        `reconnect()`; the flock keeps running."""
        for k in self._ports(port):
            self.generation[k] = self.generation.get(k, 0) + 1
        self.flock.disconnect(port)

    def reconnect(self, port: int | None = None) -> None:
        self.flock.reconnect(port)

    def _ports(self, port):
        return range(self.flock.n_ports) if port is None else [port]



SIMULATIONS: dict[str, Simulation] = {}
_registry_lock = threading.Lock()
_anonymous = itertools.count(1)


def get_simulation(name: str) -> Simulation:
    """The live simulation behind `sim://NAME…` (KeyError if none is open)."""
    return SIMULATIONS[name]


def forget_simulation(name: str) -> None:
    """Drop a named simulation; the next open of `sim://NAME` starts a fresh flock."""
    with _registry_lock:
        SIMULATIONS.pop(name, None)


def make_pose_source(*, birds: int | None, motion: str, seed: int, noise: str | None,
                     model: str, rate_hz: float = 100.0, sta_mm: float | None = None) -> Performer:
    """The performer a sim:// URL asks for (noise none/exact/0 is an exact one)."""
    return Performer(model, routine=motion, seed=seed, noise=None if noise in ("none", "exact", "0", "") else noise,
                     rate_hz=rate_hz, birds=birds, sta_mm=sta_mm)


def _parse(url: str) -> tuple[str, dict]:
    parts = urllib.parse.urlsplit(url)
    if parts.scheme.lower() != "sim":
        raise SerialException(f"expected {URL_HELP}, not {url!r}")
    q = {k: v[-1] for k, v in urllib.parse.parse_qs(parts.query, keep_blank_values=True).items()}
    known = {"birds", "motion", "seed", "noise", "model", "sta_mm", "rate", "baud", "ert", "scale", "port",
             "quaternion", "rts", "clock"}
    unknown = set(q) - known
    if unknown:
        raise SerialException(f"unknown sim:// option(s) {sorted(unknown)}; use {URL_HELP}")
    try:
        params = {
            "birds": int(q["birds"]) if "birds" in q else None,
            "motion": q.get("motion", "walk"),
            "seed": int(q.get("seed", 0)),
            "noise": q.get("noise", "tracker"),
            "model": q.get("model", "human"),
            "sta_mm": float(q["sta_mm"]) if "sta_mm" in q else None,
            "rate": float(q.get("rate", 103.0)),
            "baud": float(q["baud"]) if "baud" in q else None,
            "ert": q.get("ert", "0") in ("1", "true", "yes", "y"),
            "scale": float(q["scale"]) if "scale" in q else None,
            "port": int(q["port"]) if "port" in q else None,
            "quaternion": q.get("quaternion", "fob"),
            "rts": q.get("rts", "reset"),
        }
    except ValueError as e:
        raise SerialException(f"bad sim:// option value in {url!r} ({e}); use {URL_HELP}") from None
    if params["rts"] not in ("reset", "standby", "ignore"):
        raise SerialException(f"rts must be reset, standby or ignore, not {params['rts']!r}")
    return parts.netloc, params


def simulation_for(url: str, clock: Clock = SYSTEM) -> Simulation:
    """The simulation `sim://NAME…` names, made on `clock` when none runs (a service hands it its own clock
    before its reader opens the port). A named simulation on another clock is made afresh when no port has it
    open; SerialException when one has."""
    name, params = _parse(url)
    if not name:
        raise SerialException(f"simulation_for needs a named simulation (sim://NAME?…), not {url!r}")
    return _attach(name, params, clock, ports=False)


def _attach(name: str, params: dict, clock: Clock | None = None, ports: bool = True) -> Simulation:
    """The simulation `name` (made if none runs), with a port of it opened when `ports`. A port joins its
    simulation on that simulation's clock (`clock` None); a new one runs on `clock`, or the machine's."""
    with _registry_lock:
        named = bool(name)
        if not named:
            name = f"anonymous-{next(_anonymous)}"
        sim = SIMULATIONS.get(name)
        if clock is None:
            clock = sim.flock.clock if sim is not None else SYSTEM
        if sim is not None and sim.flock.clock is not clock:
            if any(sim.open_ports.values()):
                raise SerialException(f"sim://{name} runs on another clock and has a port open; close it first "
                                      "or name another simulation")
            sim = None
        if sim is None:
            source = make_pose_source(birds=params["birds"], motion=params["motion"],
                                      seed=params["seed"], noise=params["noise"], model=params["model"],
                                      rate_hz=params["rate"], sta_mm=params["sta_mm"])
            birds = params["birds"] or source.n_sensors
            flock = FakeFlock(source, birds=birds, ert=params["ert"], rate_hz=params["rate"],
                              baud=params["baud"] or 115200,
                              ports=birds if params["port"] is not None else 1,
                              clock=clock, scale_inches=params["scale"],
                              quaternion_convention=params["quaternion"], seed=params["seed"])
            sim = Simulation(name, flock, source, params, named)
            SIMULATIONS[name] = sim
        elif params["birds"] is not None and params["birds"] != sim.flock.n_birds:
            raise SerialException(f"sim://{name} already runs {sim.flock.n_birds} birds, not {params['birds']}")
        port = params["port"] or 0
        if not 0 <= port < sim.flock.n_ports:
            raise SerialException(f"sim://{name} has ports 0..{sim.flock.n_ports - 1} "
                                  f"(one per bird only when the first open gave &port=), not {port}")
        if not ports:
            return sim
        if not sim.flock.connected(port):
            raise SerialException(f"could not open sim://{name} port {port}: disconnected")
        sim.open_ports[port] = sim.open_ports.get(port, 0) + 1
        return sim


def _detach(sim: Simulation, port: int) -> None:
    with _registry_lock:
        sim.open_ports[port] = sim.open_ports.get(port, 1) - 1
        if not sim.named and not any(sim.open_ports.values()):
            SIMULATIONS.pop(sim.name, None)


class Serial(SerialBase):
    """A serial port whose far end is a FakeFlock (sim:// URLs)."""

    BAUDRATES = (2400, 4800, 9600, 19200, 38400, 57600, 115200, 230400, 460800, 921600)

    def __init__(self, *args, **kwargs) -> None:
        self.simulation: Simulation | None = None
        self._port_index = 0
        self._generation = 0
        self._emulated_baud: float | None = None
        self._rts_mode = "reset"
        self._cancel = threading.Event()
        super().__init__(*args, **kwargs)

    # ------------------------------------------------------------------ open / close

    def open(self) -> None:
        if self.is_open:
            raise SerialException("Port is already open.")
        if self._port is None:
            raise SerialException("Port must be configured before it can be used.")
        name, params = _parse(self._port)
        self.simulation = _attach(name, params)
        self._port_index = params["port"] or 0
        self._generation = self.simulation.generation.get(self._port_index, 0)
        self._emulated_baud = params["baud"]
        self._rts_mode = params["rts"]
        self.is_open = True
        self._reconfigure_port()
        if not self._dsrdtr:
            self._update_dtr_state()
        if not self._rtscts:
            self._update_rts_state()
        self.reset_input_buffer()

    def close(self) -> None:
        if self.is_open:
            self.is_open = False
            self._cancel.set()
            _detach(self.simulation, self._port_index)
        super().close()

    def from_url(self, url: str) -> None:
        _parse(url)  # validation only

    @property
    def flock(self) -> FakeFlock:
        return self.simulation.flock

    @property
    def performer(self) -> Performer:
        """The simulated performer this port's flock streams (it stays reachable after close)."""
        return self.simulation.source

    def _reconfigure_port(self, *args, **kwargs) -> None:
        if not self.is_open:
            return
        # The URL's baud is the bird's DIP-switch setting; without it, follow the client.
        self.flock.set_baud(self._emulated_baud or self._baudrate, self._port_index)

    def _check(self) -> None:
        if not self.is_open:
            raise PortNotOpenError()
        sim = self.simulation
        if sim.generation.get(self._port_index, 0) != self._generation or not sim.flock.connected(self._port_index):
            raise SerialException(f"read failed: sim://{sim.name} port {self._port_index} disconnected")

    # ------------------------------------------------------------------ data

    @property
    def in_waiting(self) -> int:
        self._check()
        return self.flock.in_waiting(self._port_index)

    def read(self, size: int = 1) -> bytes:
        self._check()
        self._cancel.clear()
        timeout = Timeout(self._timeout)
        data = bytearray()
        while len(data) < size:
            data += self.flock.read(self._port_index, size - len(data))
            if len(data) >= size or timeout.expired() or self._cancel.is_set():
                break
            left = timeout.time_left()
            nxt = self.flock.next_arrival(self._port_index)
            wait = 0.02 if nxt is None else max(nxt - self.flock.time(), 0.0005)
            if left is not None:
                wait = min(wait, max(left, 0.0))
            self.flock.clock.wait(self._cancel, min(wait, 0.02))
            self._check()
        return bytes(data)

    def write(self, data) -> int:
        self._check()
        data = to_bytes(data)
        return self.flock.write(data, self._port_index)

    def reset_input_buffer(self) -> None:
        if not self.is_open:
            raise PortNotOpenError()
        self.flock.discard_input(self._port_index)

    def reset_output_buffer(self) -> None:
        if not self.is_open:
            raise PortNotOpenError()

    def cancel_read(self) -> None:
        self._cancel.set()

    def flush(self) -> None:
        pass

    # ------------------------------------------------------------------ modem lines

    def _update_rts_state(self) -> None:
        if not self.is_open or self._rts_mode == "ignore" or self.flock.n_ports != 1:
            return
        # RTS high holds the bird in standby; the falling edge lets it fly from power-up state.
        if self._rts_mode == "standby":
            self.flock.set_standby(bool(self._rts_state))
        elif not self._rts_state and getattr(self, "_rts_was", True):
            self.flock.power_up_reset()
        self._rts_was = self._rts_state

    def _update_dtr_state(self) -> None:
        pass

    def _update_break_state(self) -> None:
        pass

    @property
    def cts(self) -> bool:
        return self.is_open and self.flock.connected(self._port_index)

    @property
    def dsr(self) -> bool:
        return self.cts

    @property
    def cd(self) -> bool:
        return self.cts

    @property
    def ri(self) -> bool:
        return False
