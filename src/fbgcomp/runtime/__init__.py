"""Real-time compensation: interrogator sources, pipeline, sensor health, outputs, run log.

Modules: :mod:`.hyperion` (protocol codec and client), :mod:`.simulator` (simulated
instrument), :mod:`.sources`, :mod:`.live_inputs`, :mod:`.health`, :mod:`.output_filter`,
:mod:`.pipeline`, :mod:`.outputs` (OPC UA, Modbus, LinuxCNC, the offset + Z slope form),
:mod:`.log`, :mod:`.auth` (password users), :mod:`.trust` (OPC UA client certificates),
:mod:`.realtime` and :mod:`.service` (``fbgcomp serve``). See docs/runtime.md.
"""
