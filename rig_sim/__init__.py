"""Virtual CBC rigs: ground-truth physics, embedded controller, Modbus device."""

__version__ = "0.1.0"
