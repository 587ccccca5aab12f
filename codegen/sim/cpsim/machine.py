"""CircuitPython has no `machine` module: a program that imports it fails here as it does on a board (the
emulated board's own `machine`, mpsim's, is loaded by the launcher under that name before the program starts and
then hidden)."""

raise ImportError("no module named 'machine'")
