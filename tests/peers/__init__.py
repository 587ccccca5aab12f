"""Protocol peers the deploy tests drive with the real clients: an ESP32 ROM loader (esptool) and a MicroPython
raw REPL on Node (mpremote and our uploader)."""
