"""Where the runtime's correction goes: OPC UA, Modbus TCP, LinuxCNC, and the CNC's offset+slope form."""
