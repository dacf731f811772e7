"""``fbgcomp serve``: source -> pipeline -> OPC UA + run log, in one asyncio loop.

The loop reads whatever frames have arrived, processes them as one vectorised batch, hands the
batch to the run log (non-blocking queue) and the newest sample to the OPC UA server process
(non-blocking). When no frame arrives for ``no_data_s`` the last correction is held and ramped
to zero (alarm) while the source reconnects with capped exponential back-off, unless every probe
is a live input and the model has a set without gratings: that set then runs on the probes
(degraded) until the frames are back (``probes_on_link_loss``).
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import logging
import signal
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from fbgcomp.dashboard import Dashboard
from fbgcomp.errors import InputError
from fbgcomp.io.campaign import read_campaign
from fbgcomp.models.registry import load_model
from fbgcomp.runtime import health as H
from fbgcomp.runtime import realtime
from fbgcomp.runtime.config import RuntimeConfig
from fbgcomp.runtime.live_inputs import LiveInputs, LiveTemperatures
from fbgcomp.runtime.log import RunLog
from fbgcomp.runtime.outputs.cnc_form import newest_slope
from fbgcomp.runtime.outputs.linuxcnc import LinuxCncOutput, open_cnc_output
from fbgcomp.runtime.outputs.modbus import ModbusOutput, open_modbus_output
from fbgcomp.runtime.outputs.opcua import OpcUaServer, Snapshot
from fbgcomp.runtime.pipeline import HEALTH_ALARM, HEALTH_NAMES, BatchResult, Pipeline
from fbgcomp.runtime.simulator import SignalTable, SimConfig, SimulatedHyperion
from fbgcomp.runtime.sources import (
    HyperionSource,
    ReferenceThermometers,
    ReplaySource,
    TableTemperatures,
    open_temperatures,
    parse_source_url,
)
from fbgcomp.runtime.summary import startup_summary
from fbgcomp.runtime.windows import PeakMapper, SensorBatch

log = logging.getLogger("fbgcomp.runtime")


#: A frame stamped this much (s) before the last one run without gratings while the link was
#: lost is an instrument clock set back, not a reconnect's jitter: it is taken, not dropped.
CLOCK_SET_BACK_S = 5.0


def model_meta(model, pipeline: Pipeline, temperature_probes=None) -> dict:
    """The run log's ``meta.json``: model, sensors, probes, model sets, names of the codes and
    limits in force.
    """

    def dump(s):
        return s.model_dump(mode="json") if hasattr(s, "model_dump") else dict(vars(s))

    return {
        "format": "fbgcomp-runlog",
        "version": 1,
        "model_id": model.model_id,
        "sensor_names": pipeline.sensor_names,
        "probe_names": pipeline.probe_names,
        # the slow inputs that are measured heat inputs (W, heat.csv), not probes (°C)
        "heat_inputs": list(getattr(model, "heat_channels", [])),
        "sensors": [dump(s) for s in model.sensors],
        "temperature_probes": temperature_probes,
        "model_sets": [sorted(s) for s in pipeline.model_sets],
        "health_names": list(HEALTH_NAMES),
        "status_names": list(H.STATUS_NAMES),
        "flag_names": {str(bit): name for bit, name in H.FLAG_NAMES.items()},
        "max_correction_um": [float(v) for v in pipeline.max_correction_um],
        "max_slew_um_per_s": [float(v) for v in pipeline.max_slew_um_per_s],
        "zero_window_s": pipeline.zero_window_s,
    }


def correction_eu_ranges(max_correction_um) -> dict[str, tuple[float, float]]:
    """The OPC UA EURange of each axis's correction from the cap in force at start-up
    (``CorrectionX_um`` in +-max_correction_um[0], ...; an axis without a cap keeps the
    default range)."""
    return {
        f"Correction.{a}": (-float(c), float(c))
        for a, c in zip("XYZ", max_correction_um)
        if np.isfinite(c) and c > 0
    }


class Service:
    """One compensation service. ``run`` returns when the duration ends or on stop()."""

    def __init__(self, config: RuntimeConfig, model=None, announce: Callable[[str], None] | None = None):
        self.config = config
        # called once with startup_summary() when everything has started (serve prints it)
        self.announce = announce
        self.model = model if model is not None else self._load_model(config.model)
        self.pipeline = Pipeline(self.model, config.pipeline)
        self.model_id = self.model.model_id
        self.mapper = PeakMapper.for_sensors(self.model.sensors, config.source.window_nm)
        # the model's <sensor>_ref probes come from the reference gratings' peaks, the others
        # from the temperature source
        self.thermometers = ReferenceThermometers(
            self.pipeline.probe_names, self.model.sensors, self.mapper.reference_probes
        )
        self.frames = 0
        self.batches = 0
        self.busy_s = 0.0
        self.last_result: BatchResult | None = None
        self.opc: OpcUaServer | None = None
        self.dashboard: Dashboard | None = None  # when configured
        self.cnc: LinuxCncOutput | None = None  # --cnc
        self.modbus: ModbusOutput | None = None  # [modbus]
        self.live: LiveInputs | None = None  # [temperatures.*], [position]
        self.z_mm: float | None = None  # the Z position given to the model on the last batch
        self.input_status = ""  # live inputs: "inputs OK" or which are stale
        self.frames_waiting = 0  # frames dropped before zeroing, live inputs not up
        self._enabled = True  # used only without OPC UA
        self.runlog: RunLog | None = None
        self.sim: SimulatedHyperion | None = None
        self._stop = asyncio.Event()
        self._offset_s = 0.0  # wall clock - instrument clock, for no-data hold times
        self._no_data_since: float | None = None
        # the instrument time of the last frame without gratings run while the link was lost
        # (_probes_through_loss); frames stamped before it are dropped when the link is back
        self._tick_t: float | None = None
        self.ticks = 0  # frames without gratings run while the link was lost

    @staticmethod
    def _load_model(path):
        if not path:
            raise InputError("no model given", column="--model")
        return load_model(path)

    # -- set-up
    async def _open_source(self):
        cfg = self.config.source
        scheme, opts = parse_source_url(cfg.url)
        probes = self.thermometers.real_probes
        live = LiveInputs(self.config.temperatures, self.config.position, probes, self.cnc)
        self.live = live if live else None
        if self.live is not None and self.live.has_position and not self.pipeline.uses_z:
            log.warning("[position]: %s", self.pipeline.z_note)
        # the probes no live input supplies come from --temperatures (or the replayed campaign)
        probes = [p for p in probes if p not in live.probe_reader]
        temps = None
        probe_specs = None
        if scheme == "hyperion":
            src = HyperionSource(
                opts["host"],
                int(opts["stream_port"]),
                int(opts["command_port"]),
                self.mapper,
                cfg.backoff_initial_s,
                cfg.backoff_max_s,
                cfg.stall_timeout_s,
            )
        elif scheme == "replay":
            src = ReplaySource(
                opts["path"],
                self.pipeline.sensor_names,
                probes,
                float(opts.get("speed", cfg.speed)),
                loop=opts.get("loop", str(cfg.loop)).lower() in ("1", "true"),
                reference_probes=self.mapper.reference_probes,
            )
            temps = src.temperatures
            probe_specs = _probe_specs(opts["path"])
        else:  # sim://DIR: an in-process simulated instrument replaying the campaign
            table = SignalTable.from_campaign(opts["path"])
            speed = float(opts.get("speed", cfg.speed))
            loop = opts.get("loop", str(cfg.loop)).lower() in ("1", "true")
            sim = SimulatedHyperion(
                table,
                SimConfig(
                    rate_hz=float(opts.get("rate", 1000)),
                    channels=int(opts.get("channels", 1)),
                    speed=speed,
                    loop=loop,
                ),
            )
            await sim.start()
            self.sim = sim
            src = HyperionSource(
                "127.0.0.1",
                sim.stream_port,
                sim.command_port,
                self.mapper,
                cfg.backoff_initial_s,
                cfg.backoff_max_s,
                cfg.stall_timeout_s,
            )
            if probes:
                temps = TableTemperatures.from_campaign(opts["path"], probes, speed, loop)
                temps.origin = sim._t0 - table.time_s[0] / speed
            probe_specs = _probe_specs(opts["path"])
        if cfg.temperatures is not None or temps is None:
            if probes and cfg.temperatures is None and live.probes:
                raise InputError(
                    f"probe {probes[0]} has no source: name it in "
                    "[temperatures.opcua] nodes or [temperatures.modbus] registers, "
                    "or give --temperatures",
                    column="--temperatures",
                )
            temps = open_temperatures(cfg.temperatures, probes, cfg.speed, cfg.loop)
            if cfg.temperatures and Path(cfg.temperatures).is_dir():
                probe_specs = _probe_specs(cfg.temperatures)
        if live.probes:
            temps = LiveTemperatures(self.thermometers.real_probes, live, temps)
        return src, temps, probe_specs

    # -- model reload (OPC UA ReloadModel, run on this loop through run_coroutine_threadsafe)
    async def reload(self, path: str) -> str:
        """Load model file ``path`` (empty: the one serve was started with) in place of the running
        model, keeping the zero state; it must expect the same sensors and probes.
        """
        path = path or self.config.model
        loop = asyncio.get_running_loop()
        new = await loop.run_in_executor(None, self._load_model, path)
        if (
            list(new.sensor_names) != self.pipeline.sensor_names
            or list(new.probe_names) != self.pipeline.probe_names
        ):
            raise InputError("reloaded model expects other sensors or probes", file=path)
        pipe = Pipeline(new, self.config.pipeline)
        # keep the running zero state, sensor history and re-admission state: the machine
        # has not been re-zeroed
        pipe.continue_from(self.pipeline)
        self.model, self.pipeline, self.model_id = new, pipe, new.model_id
        if self.opc is not None:
            self.opc.model_id = self.model_id
        log.info("model reloaded from %s (%s)", path, self.model_id)
        return f"loaded {self.model_id}"

    def stop(self) -> None:
        """Ask :meth:`run` to end (signal handlers call it)."""
        self._stop.set()

    @property
    def enabled(self) -> bool:
        """Whether the correction output is on (the OPC UA server's ``Enabled`` when it runs)."""
        return self.opc.enabled if self.opc is not None else self._enabled

    def set_enabled(self, value: bool) -> bool:
        """Switch the correction output (dashboard control, from its thread). With OPC UA the
        server's ``Enabled`` node is written, so the CNC and the dashboard see one state."""
        value = bool(value)
        opc = self.opc
        if opc is not None:
            opc.set_enabled(value)  # the OPC UA process writes its Enabled node
        else:
            self._enabled = value
        return self.enabled

    # -- main loop
    async def run(self, duration_s: float | None = None) -> None:
        """Start the outputs and the source, then process batches until stopped, the source ends or
        ``duration_s`` has passed; everything started is stopped again on the way out.
        """
        main_loop = asyncio.get_running_loop()
        self.modbus = open_modbus_output(self.config.modbus)
        if self.modbus is not None:
            self.modbus.start()  # a busy port fails before anything else runs
        if self.config.opcua_enabled:
            # first: the slowest to start, and a busy port must fail before anything runs
            self.opc = OpcUaServer(
                self.config.opcua,
                self.pipeline.sensor_names,
                self.model_id,
                on_reload=self.reload,
                main_loop=main_loop,
                eu_ranges=correction_eu_ranges(self.pipeline.max_correction_um),
            )
            await main_loop.run_in_executor(None, self.opc.start)
        try:
            self.cnc = open_cnc_output(self.config.cnc)  # started below; read by [position]
            source, temps, probe_specs = await self._open_source()
        except BaseException:
            if self.opc is not None:
                await main_loop.run_in_executor(None, self.opc.stop)
            if self.modbus is not None:
                self.modbus.stop()
            raise
        self.source, self.temps = source, temps
        if self.config.log.dir:
            self.runlog = RunLog(
                self.config.log.dir,
                model_meta(self.model, self.pipeline, probe_specs),
                self.config.log.flush_s,
                fsync=self.config.log.fsync,
            )
        if self.config.dashboard.listen:
            self.dashboard = Dashboard(
                self.config.dashboard,
                self.pipeline.sensor_names,
                self.pipeline.probe_names,
                self.model_id,
                control=self.set_enabled,
                enabled=lambda: self.enabled,
                log_dir=self.config.log.dir,
            )
            self.dashboard.start()
        if self.cnc is not None:
            self.cnc.start()
        if self.live is not None:
            self.live.start()
        if self.announce is not None:
            self.announce(self.startup_summary())
        queue: asyncio.Queue[SensorBatch | None] = asyncio.Queue()

        async def pump():
            try:
                async for b in source.batches():
                    queue.put_nowait(b)
            finally:
                queue.put_nowait(None)

        pump_task = asyncio.create_task(pump())
        # everything set up so far lives as long as the service: out of the cyclic collector,
        # whose full passes over it would stall the loop
        gc.collect()
        gc.freeze()
        end = None if duration_s is None else time.monotonic() + duration_s
        try:
            while not self._stop.is_set():
                # once data has stopped, tick at 50 Hz so the ramp to zero is smooth
                timeout = (
                    min(self.config.source.no_data_s, 0.02)
                    if self._no_data_since
                    else self.config.source.no_data_s
                )
                if end is not None:
                    remaining = end - time.monotonic()
                    if remaining <= 0:
                        break
                    timeout = min(timeout, remaining)
                try:
                    first = await asyncio.wait_for(queue.get(), timeout)
                except TimeoutError:
                    if end is None or time.monotonic() < end:
                        self._no_data_since = self._no_data_since or time.monotonic()
                        self._no_data()
                    continue
                self._no_data_since = None
                items = [first]
                while not queue.empty():
                    items.append(queue.get_nowait())
                batches = [i for i in items if i is not None]
                if len(batches) < len(items):
                    if batches:
                        self._process(SensorBatch.concat(batches))
                    break  # the source ended (replay finished)
                self._process(SensorBatch.concat(batches))
        finally:
            if self.cnc is not None:
                self.cnc.stop()  # the CNC ramps its offsets to zero without waiting for a timeout
            if self.live is not None:
                await self.live.close()
            if self.modbus is not None:
                await main_loop.run_in_executor(None, self.modbus.stop)
            await source.close()
            pump_task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await pump_task
            if self.sim is not None:
                await self.sim.stop()
            if self.dashboard is not None:
                await main_loop.run_in_executor(None, self.dashboard.stop)
            if self.opc is not None:
                await main_loop.run_in_executor(None, self.opc.stop)
            if self.runlog is not None:
                await main_loop.run_in_executor(None, self.runlog.close)

    def startup_summary(self) -> str:
        """One line on what this service reads, publishes, applies and lets others change
        (:func:`fbgcomp.runtime.summary.startup_summary`)."""
        return startup_summary(self)

    def _process(self, batch: SensorBatch, tick: bool = False, temps=None) -> None:
        """Run ``batch`` through the pipeline, log and publish it; ``tick``: a frame without
        gratings run while the link is lost (:meth:`_probes_through_loss`), with its ``temps``."""
        if not tick and self._tick_t is not None:
            # the link is back: the model's filters already ran to the last frame without
            # gratings, so frames stamped before it (a reconnect's first, a clock's jitter) go;
            # frames far older are an instrument clock set back (a reboot), taken as before
            keep = (batch.time_s > self._tick_t) | (batch.time_s < self._tick_t - CLOCK_SET_BACK_S)
            if not keep.any():
                return
            if not keep.all():
                batch = batch.take(keep)
            self._tick_t = None
        if len(batch) == 0:
            return
        t0 = time.perf_counter()
        enabled = self.enabled
        if temps is None:
            temps = self.thermometers.temperature_C(self.temps.latest(batch.time_s), batch.reference_nm)
        z = None
        if self.live is not None:
            # the newest Z for the whole batch (a batch lasts milliseconds); NaN when stale
            z = self.live.z_mm()
            self.input_status = self.live.check(getattr(self.temps, "last_live", {}), z)
        self.z_mm = z
        if (
            self.live is not None
            and not self.pipeline.zeroed
            and self.pipeline._t_first is None
            and not self._inputs_ready(temps, z)
        ):
            # the zero state is the mean of the first seconds: it must not start before every
            # live input has a value (an OPC UA or Modbus link takes a moment to come up), or
            # a probe without a zero would leave the model unusable for the whole run
            self.frames_waiting += len(batch)
            return
        res = self.pipeline.process(
            batch.time_s, batch.wavelength_nm, batch.peak_count, batch.near_count, temps, enabled, z_axis_mm=z
        )
        if tick:
            self.ticks += len(batch)
        else:
            self._offset_s = batch.received_s - float(batch.time_s[-1])
            self.frames += len(batch)
            self.batches += 1
        self.last_result = res
        if self.runlog is not None:
            self.runlog.submit(batch, res, enabled, z)
        self._publish(res, batch.wavelength_nm[-1], batch.received_s)
        self.busy_s += time.perf_counter() - t0

    def _inputs_ready(self, temps: np.ndarray, z) -> bool:
        """Every live probe and (for a model that depends on it) the Z position has a value."""
        if not np.isfinite(list(getattr(self.temps, "last_live", {}).values())).all():
            return False
        return z is None or not self.pipeline.uses_z or bool(np.isfinite(z))

    def _no_data(self) -> None:
        """No frame for no_data_s (link lost): the probes carry on where they can
        (:meth:`_probes_through_loss`); else hold / ramp the last correction (alarm), sensors
        missing."""
        if not self.pipeline.zeroed:
            return
        if self._probes_through_loss():
            return
        S = len(self.pipeline.sensor_names)
        res = self.pipeline.no_data(time.time() - self._offset_s, self.enabled)
        self.last_result = res
        self._publish(res, np.full(S, np.nan), time.time())

    def _probes_through_loss(self) -> bool:
        """With the interrogator's link lost, one frame without gratings through the pipeline, at
        the instrument time now, when every probe is a live input (OPC UA, Modbus: a path of its
        own, stale after its ``stale_s``) and the model stores a set without every grating and
        without the probes that have no reading. The thermal correction then goes on from the
        probes (health DEGRADED, the set named) where it was held and ramped to zero in
        ``ramp_s``: on ram2's thermal_b, 60 µm of dz drift left uncompensated for as long as the
        link stays down. The load part goes as it did: the set reads no force. Returns whether
        the frame ran (``source.probes_on_link_loss``)."""
        temps = self.temps
        if not self.config.source.probes_on_link_loss or not getattr(temps, "all_live", False):
            return False
        now = time.time()
        t = now - self._offset_s
        if self._tick_t is not None:
            t = max(t, self._tick_t + 1e-6)  # the filters' clock never runs back
        time_s = np.array([t])
        S, R = len(self.pipeline.sensor_names), len(self.mapper.reference_probes)
        refs = np.full((1, R), np.nan) if R else None
        probes = self.thermometers.temperature_C(temps.latest(time_s), refs)
        if self.pipeline.set_without(np.concatenate([np.ones(S, bool), ~np.isfinite(probes[0])])) < 0:
            return False
        none = np.zeros((1, S), np.int8)
        self._process(SensorBatch(time_s, np.full((1, S), np.nan), none, none, now, refs), True, probes)
        self._tick_t = t
        return True

    def _publish(self, res, wavelength_nm, received_s) -> None:
        """Newest sample to the outputs; each only stores it (never blocks this loop)."""
        if self.opc is None and self.dashboard is None and self.cnc is None and self.modbus is None:
            return
        snap = self._snapshot(res, wavelength_nm, received_s)
        if self.cnc is not None:
            self.cnc.publish(snap, self.enabled)
        if self.modbus is not None or self.opc is not None:  # offset + Z slope, the form a
            # CNC's PLC takes
            z = self.z_mm if self.z_mm is not None and np.isfinite(self.z_mm) else None
            slope, z_ref = newest_slope(self.pipeline, res, wavelength_nm, z)
        if self.modbus is not None:
            self.modbus.publish(snap, self.enabled, slope, z_ref)
        if self.opc is not None:  # the Modbus output's limited values, else its limits
            self.opc.publish(snap, self.enabled, slope, z_ref, self.modbus or self.config.modbus)
        if self.dashboard is not None:
            self.dashboard.publish(snap, res.temperature_C[-1], self.pipeline)

    def _snapshot(self, res, wavelength_nm, received_s) -> Snapshot:
        k = int(res.model_set[-1])
        fallback = ",".join(sorted(self.pipeline.model_sets[k])) if k > 0 else ""
        h = int(res.health[-1])
        # plain Python numbers: the snapshot is pickled to the OPC UA process per update
        return Snapshot(
            sample_time_s=float(res.time_s[-1]),
            correction_um=tuple(res.correction_um[-1].tolist()),
            deviation_um=tuple(res.deviation_um[-1].tolist()),
            half_width_um=tuple(res.half_width_um[-1].tolist()),
            expected_rms_um=tuple(res.expected_rms_um[-1].tolist()),
            health=HEALTH_NAMES[h],
            fallback=fallback,
            alarm=bool(h == HEALTH_ALARM),
            output_flags=tuple(int(v) for v in res.output_flags[-1].tolist()),
            sensor_status=[H.STATUS_NAMES[c] for c in res.sensor_status[-1].tolist()],
            sensor_wavelength_nm=np.asarray(wavelength_nm, float).tolist(),
            source_status=str(getattr(self.source, "status", ""))
            + (f"; {self.input_status}" if self.input_status else ""),
            frames=int(self.frames),
            model_id=self.model_id,
            received_s=float(received_s),
        )


def _probe_specs(folder):
    try:
        c = read_campaign(folder)
        return [
            p.model_dump(mode="json") if hasattr(p, "model_dump") else dict(vars(p))
            for p in c.meta.temperature_probes
        ]
    except Exception:
        return None


def run_service(
    config: RuntimeConfig, duration_s: float | None = None, announce: Callable[[str], None] | None = None
) -> Service:
    """Run until SIGINT / SIGTERM (graceful: the run log is flushed) or ``duration_s``;
    ``announce`` is given the one-line start-up summary (:meth:`Service.startup_summary`)."""
    # The log writer (and other outputs) run in threads: when one of them holds the GIL, hand
    # it back within 1 ms (default 5 ms) so a frame waiting to be processed is not held up.
    sys.setswitchinterval(0.001)
    # pinned core, SCHED_FIFO where permitted (else one warning and normal priority), gc
    # threshold: before the OPC UA process starts, so it inherits them
    for line in realtime.apply(config.realtime):
        log.info("real time: %s", line)
    service = Service(config, announce=announce)

    async def main():
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            with contextlib.suppress(NotImplementedError, RuntimeError):  # not on this platform / thread
                loop.add_signal_handler(sig, service.stop)
        await service.run(duration_s)

    asyncio.run(main())
    return service
