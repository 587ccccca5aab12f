"""Emulated CircuitPython `board`: the board's pins by the names of its pins.c (from the scenario), board_id."""

import firmware
import microcontroller

board_id = firmware.settings().get("board_id", "")

for _name, _gpio in firmware.settings().get("pins", {}).items():
    globals()[_name] = microcontroller.board_pin(_name, _gpio)
