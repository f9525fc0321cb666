"""OpenCL C sources of the renderer, shipped as package data (see runtime.load_source)."""
