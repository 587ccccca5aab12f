"""deadreckon: board YAML -> MicroPython dead-reckoning app + native C kernel.

The pipeline, one direction, one package per stage:

    board/     YAML -> validated Board model (reader with positions, schema, pin and board rules)
    generate   Board -> render context -> templates/ -> OUT/app (MicroPython), OUT/native (C), MANIFEST.json
    deploy/    OUT -> .mpy, native module, LittleFS image -> onto the board (esptool, raw REPL)
    kernel/    the algorithms' float64 references and the C kernel on the host (cffi)
    sim/       sensors and GPS modelled, the references and the generated app (on the emulated board, mpsim) scored
    post/      a logged run aligned to East-North-Up from GPS Doppler, reconstructed
"""

__version__ = "0.1.0"
