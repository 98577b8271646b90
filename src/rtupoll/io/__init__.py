"""The only I/O with a bus: the pymodbus adapter, serial ports, the bus interface."""
