"""The CBC host: a rig client from the register map, a real-time engine, CBC plans,
and the HDF5 campaign log."""

__version__ = "0.1.0"
