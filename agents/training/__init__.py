"""The run machinery: configs, the registry, the driver, checkpoints, sweeps and `snac train`."""
