"""Real-time compensation: interrogator sources, pipeline, sensor health, OPC UA output, run log.

Modules: :mod:`.hyperion` (protocol codec and client), :mod:`.simulator` (simulated
instrument), :mod:`.sources`, :mod:`.health`, :mod:`.pipeline`, :mod:`.opcua`, :mod:`.log`,
:mod:`.service` and :mod:`.cli`. See docs/runtime.md.
"""
