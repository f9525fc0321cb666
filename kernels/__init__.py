"""OpenCL C sources of the renderer, shipped as package data (found by coin_cl.engine.devices.kernel_dir)."""
