"""The rig as a device: register map (the datasheet), register access, transports."""
