"""deadreckon: board YAML -> MicroPython dead-reckoning app + native C kernel."""

__version__ = "0.1.0"
