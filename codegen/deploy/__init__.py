"""Stage 3 of the pipeline, after `generate`: the tree compiled for the board (build: mpy-cross, the native module,
fsimage: the LittleFS image) and put onto it (flash: esptool; upload: the raw REPL)."""
