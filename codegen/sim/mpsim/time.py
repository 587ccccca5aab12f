"""A `time` module for the unix-port MicroPython whose clock the test controls.

Virtual microseconds advance only when the program sleeps, talks to an emulated peripheral, or reads the clock
(a few microseconds per read), so a run is deterministic. ticks_* wrap with the ESP32's period (2**30), and the
scenario may start the counter just below the wrap. When the scenario's duration is over, the clock ends the run
(the world is finalised and SystemExit is raised; the app's `except Exception` blocks do not catch it).
"""

TICKS_PERIOD = 1 << 30
_HALF = TICKS_PERIOD >> 1
_MASK = TICKS_PERIOD - 1
READ_COST_US = 3  # each clock read costs the program this much virtual time

class Reset(BaseException):
    """The board resets (machine.reset(), the watchdog): not an Exception, so no app handler catches it; the
    launcher boots the app again with the world as it is (launch.py)."""


_watchdog = -1  # virtual us by which the app must feed the watchdog (-1: none armed)
_watchdog_us = 0
reset_cause = 1  # machine.reset_cause() after the next boot (1 power-on, 3 watchdog, 5 soft)
halted = False  # between a reset and the next boot: the old code's last gasps (finally blocks) reach no flash

_now = 0  # virtual microseconds since the start of the run (unbounded)
_start_ticks = 0  # ticks_us() value at _now == 0
_end = -1  # end of the run in virtual us (-1: never)
_epoch_s = 0  # time() at _now == 0
_on_end = None


def _configure(start_ticks_us, end_us, epoch_s, on_end):
    global _start_ticks, _end, _epoch_s, _on_end
    _start_ticks = start_ticks_us & _MASK
    _end = end_us
    _epoch_s = epoch_s
    _on_end = on_end


def now():
    """Virtual microseconds since the start of the run (for the emulated peripherals)."""
    return _now


def advance(us):
    """Move the clock on by `us`; on the way, run the timers' callbacks that fall due (as a soft IRQ runs between
    bytecodes), raise KeyboardInterrupt at an interrupt's time (Ctrl-C), and the watchdog's reset if unfed."""
    global _now, _end, _watchdog, reset_cause
    later = _now + int(us)
    while True:
        step = later
        if 0 <= _watchdog < step:  # the watchdog fires inside this wait, not after it
            step = _watchdog + 1
        due = _next_timer()
        if due is not None and due[0] <= step and not _in_callback:
            _now = max(_now, due[0])
            _run_timer(due)
            continue
        if _interrupts and _interrupts[0] <= step:
            _now = max(_now, _interrupts.pop(0))
            raise KeyboardInterrupt()
        _now = step
        break
    if 0 <= _end <= _now:
        _end = -1
        if _on_end is not None:
            _on_end()
        raise SystemExit(0)
    if 0 <= _watchdog < _now:
        _watchdog = -1
        reset_cause = 3
        raise signal_reset("watchdog")


# machine.Timer's periodic callbacks ([due us, period us, callback, timer]) and the moments (virtual us) a Ctrl-C
# arrives (the scenario's "interrupts_s")
_timers = []
_interrupts = []
_in_callback = False


def _next_timer():
    return min(_timers, key=lambda t: t[0]) if _timers else None


def _run_timer(entry):
    global _in_callback
    entry[0] += entry[1]
    _in_callback = True
    try:
        entry[2](entry[3])
    finally:
        _in_callback = False


def add_timer(period_us, callback, timer):
    remove_timer(timer)
    _timers.append([_now + period_us, period_us, callback, timer])


def remove_timer(timer):
    _timers[:] = [t for t in _timers if t[3] is not timer]


def clear_timers():
    """A reset stops every timer (MicroPython deinitialises them on a soft reset too)."""
    _timers[:] = []


def interrupt_at(times_us):
    _interrupts[:] = sorted(int(t) for t in times_us)


def signal_reset(why):
    global halted
    halted = True
    return Reset(why)


def arm_watchdog(timeout_us):
    global _watchdog, _watchdog_us
    _watchdog_us = timeout_us
    _watchdog = _now + timeout_us


def feed_watchdog():
    global _watchdog
    if _watchdog >= 0:
        _watchdog = _now + _watchdog_us


def disarm_watchdog():
    global _watchdog
    _watchdog = -1


def ticks_us():
    advance(READ_COST_US)
    return (_start_ticks + _now) & _MASK


def ticks_ms():
    advance(READ_COST_US)
    return ((_start_ticks + _now) // 1000) & _MASK


def ticks_cpu():
    return ticks_us()


def ticks_add(ticks, delta):
    return (ticks + delta) & _MASK


def ticks_diff(end, start):
    return ((end - start + _HALF) & _MASK) - _HALF


def sleep_us(us):
    if us > 0:
        advance(us)


def sleep_ms(ms):
    if ms > 0:
        advance(ms * 1000)


def sleep(s):
    if s > 0:
        advance(s * 1000000)


def time():
    return _epoch_s + _now // 1000000


def time_ns():
    return (_epoch_s * 1000000 + _now) * 1000


def gmtime(secs=None):
    # 2000-01-01 based like the ESP32 port; only used for file names and diagnostics
    if secs is None:
        secs = time()
    days, rem = divmod(int(secs), 86400)
    hh, rem = divmod(rem, 3600)
    mm, ss = divmod(rem, 60)
    y = 2000
    while True:
        ylen = 366 if (y % 4 == 0 and (y % 100 != 0 or y % 400 == 0)) else 365
        if days < ylen:
            break
        days -= ylen
        y += 1
    mdays = [31, 29 if ylen == 366 else 28, 31, 30, 31, 30, 31, 31, 30, 31, 30, 31]
    m = 0
    while days >= mdays[m]:
        days -= mdays[m]
        m += 1
    return (y, m + 1, days + 1, hh, mm, ss, 0, 0)


localtime = gmtime
