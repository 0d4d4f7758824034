"""The simulated rig: one world, four instrument servers on loopback.

>>> with SimulatedRig(speed=None, seed=1) as rig:          # lockstep, deterministic
...     rig.addresses["generator"]                          # 'socket://127.0.0.1:PORT'

Addresses are what a real rig's config would hold: the SCPI generator and the
two laser controllers as pyserial URLs (``socket://host:port``; with
``pty=True`` also a pty device path each), the amplifier as ``host:port`` for
Modbus TCP.
"""
from __future__ import annotations

from pathlib import Path

from sim_backend import laser_sensor, signal_generator
from sim_backend.laser_sensor import SimLaserSensor
from sim_backend.line_server import LineServer
from sim_backend.power_amplifier import SimPowerAmplifier
from sim_backend.signal_generator import SimSignalGenerator
from sim_backend.world import World

INSTRUMENTS = ("generator", "amplifier", "sensor_base", "sensor_tip")


class SimulatedRig:
    def __init__(self, config: dict | str | Path | None = None, speed: float | None = 1.0,
                 seed: int = 0, pty: bool = False, host: str = "127.0.0.1",
                 ports: dict[str, int] | None = None):
        unknown = set(ports or {}) - set(INSTRUMENTS)
        if unknown:
            raise ValueError(f"unknown instrument(s) in ports: {sorted(unknown)}")
        self.world = World(config, speed=speed, seed=seed)
        self.host = host
        self._ports = dict(ports or {})
        self._pty = pty
        self.generator = SimSignalGenerator(self.world)
        self.sensors = {
            "sensor_base": SimLaserSensor(self.world, 0, "base"),
            "sensor_tip": SimLaserSensor(self.world, 1, "tip"),
        }
        self.amplifier = SimPowerAmplifier(self.world, host=host, port=self._ports.get("amplifier", 0))
        self.servers: dict[str, LineServer] = {}
        self.started = False

    def start(self) -> "SimulatedRig":
        if self.started:
            return self
        try:
            gen = LineServer("generator", self.generator.handle, "\n", self.host,
                             self._ports.get("generator", 0), pty=self._pty,
                             line_too_long=signal_generator.LINE_TOO_LONG)
            gen.on_kill = self.generator.power_off
            self.servers["generator"] = gen.start()
            for name, sensor in self.sensors.items():
                self.servers[name] = LineServer(name, sensor.handle, "\r", self.host, self._ports.get(name, 0),
                                                pty=self._pty, line_too_long=laser_sensor.LINE_TOO_LONG).start()
            self.amplifier.start()
        except OSError:  # a port in use (the message names the instrument and the port)
            self.stop()
            raise
        self.world.start_clock()
        self.started = True
        return self

    def stop(self) -> None:
        self.world.stop_clock()
        for server in self.servers.values():
            server.stop()
        self.amplifier.stop()
        self.started = False

    def __enter__(self) -> "SimulatedRig":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    @property
    def addresses(self) -> dict[str, str]:
        out = {name: self.servers[name].url for name in ("generator", "sensor_base", "sensor_tip")
               if name in self.servers}
        out["amplifier"] = self.amplifier.address
        return {k: out[k] for k in INSTRUMENTS if k in out}

    @property
    def pty_paths(self) -> dict[str, str]:
        return {name: s.pty_path for name, s in self.servers.items() if s.pty_path}

    def kill(self, name: str) -> None:
        """Abruptly close one instrument server (the instrument 'dies')."""
        if name == "amplifier":
            self.amplifier.kill()
        elif name in self.servers:
            self.servers[name].kill()
        else:
            raise ValueError(f"unknown instrument {name!r}; one of {INSTRUMENTS}")
