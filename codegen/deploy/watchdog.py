"""The board's watchdog, from the host's side: after `RawRepl.enter()` interrupted the app, make sure a timer keeps
feeding the watchdog the app started (a started machine.WDT cannot be stopped), so a transfer through the REPL may
take far longer than its timeout.

The app hands its watchdog to a timer itself when Ctrl-C stops it (templates/micropython/app.py.j2,
hold_watchdog). This is the second line, for a Ctrl-C that lands before the app's handler runs (while main.py
imports the app after a soft reset, with the watchdog of the previous run still counting) or an app built before
the handover: the host takes the app's watchdog (`app._wdt`) or, where the app's board_config is on the board,
the running watchdog again with the app's own timeout (machine.WDT(timeout) on a running watchdog sets it up
again, it does not start a second one), and feeds it from a timer. A board without the app's board_config gets
no watchdog from the host. CircuitPython stops its watchdog itself when code.py ends by Ctrl-C, and has no
`machine`: nothing is done there. docs/watchdog.md has the whole picture.
"""

from __future__ import annotations

HOLD_SCRIPT = """
import sys
def _dr_hold():
    a = sys.modules.get('app')
    if a is not None and getattr(a, '_holder', None) is not None:
        return 'app'
    try:
        import machine
        import board_config
        ms = board_config.WATCHDOG_MS
    except (ImportError, AttributeError):
        return 'none'
    w = getattr(a, '_wdt', None) if a is not None else None
    if w is None:
        try:
            w = machine.WDT(timeout=ms)
        except Exception:
            return 'none'
    w.feed()
    for i in (-1, 0):
        try:
            t = machine.Timer(i)
            t.init(mode=machine.Timer.PERIODIC, period=max(100, ms // 4), callback=lambda t: w.feed())
        except Exception:
            continue
        if a is not None:
            a._holder = t
        globals()['_dr_holder'] = t
        return 'host'
    return 'none'
print(_dr_hold())
"""


def hold_watchdog(repl) -> str:
    """Run HOLD_SCRIPT on the board in the raw REPL `repl`; returns who feeds the watchdog now: 'app' (its own
    handover), 'host' (the timer started here) or 'none' (no app watchdog to feed, or no timer)."""
    answer = repl.exec(HOLD_SCRIPT, timeout=10.0).decode("utf-8", "replace").strip()
    return answer.splitlines()[-1] if answer else "none"
