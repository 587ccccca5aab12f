"""The emulated board's clock for the app's own work (codegen/sim/boardclock.py states the model and its sources).

`install(costs)` wraps, from outside, the operations of the generated app that the cost table covers, so that each
call advances the virtual clock by its cost on the board (after the call: a sample's read time is taken inside it,
a window's time is read after it). The app itself is not changed: it finds the time these operations take through
time.ticks_us(), as it would on the board. The buses (I2C, UART) and the flash charge their own time in machine.py
and simworld.py.
"""

import time

_charged = {}  # operation -> [calls, microseconds] (the run's totals, traced at the end)


def _charge(name, us):
    if us > 0:
        entry = _charged.get(name)
        if entry is None:
            entry = _charged[name] = [0, 0.0]
        entry[0] += 1
        entry[1] += us
        time.advance(us)


def totals():
    return _charged


def _line(cost, m):
    return cost[0] + cost[1] * m


_inside = [0]  # kernel calls in progress: the fallback's functions call each other through the module, and the
# cost measured for the outer call holds the inner ones


def _kernel(dr, kind, costs):
    k = costs[kind]

    def per_sample(name, fn, cost, samples_of):
        def call(*args):
            _inside[0] += 1
            try:
                result = fn(*args)
            finally:
                _inside[0] -= 1
            if not _inside[0]:
                _charge(kind + "." + name, _line(cost, samples_of(args)))
            return result
        return call

    def fixed(name, fn, cost):
        def call(*args):
            _inside[0] += 1
            try:
                result = fn(*args)
            finally:
                _inside[0] -= 1
            if not _inside[0]:
                _charge(kind + "." + name, cost)
            return result
        return call

    by_dt = lambda args: len(args[2])  # noqa: E731  (samples, dt_us, out): m = len(dt_us)
    by_samples = lambda args: len(args[1]) // 6  # noqa: E731
    if hasattr(dr, "fused_process"):
        dr.fused_process = per_sample("fused_process", dr.fused_process, k["fused_process"], by_dt)
        dr.fused_calibrate = per_sample("fused_calibrate", dr.fused_calibrate, k["fused_calibrate"], by_samples)
        dr.fused_gps = fixed("fused_fix", dr.fused_gps, k["fused_fix"])  # with its fused_position
    dr.process = per_sample("process", dr.process, k["process"], by_dt)
    dr.calibrate = per_sample("calibrate", dr.calibrate, k["calibrate"], by_samples)
    dr.set_velocity = fixed("set_velocity", dr.set_velocity, k["set_velocity"])
    dr.offset_latlon = fixed("offset_latlon", dr.offset_latlon, k["offset_latlon"])


def install(costs):
    """Meter the app (imported here) with `costs`: {operation: board microseconds} (codegen/sim/boardclock.py)."""
    import app
    import nmea

    try:
        import display
    except ImportError:  # a board without a display
        display = None

    App = app.App
    mode = "fused" if app.FUSED else "seed"

    step = App.step

    def metered_step(self):
        step(self)
        _charge("step", costs["step"])

    App.step = metered_step

    sample = App._sample

    def metered_sample(self):
        got = sample(self)
        if got:
            _charge("sample", costs["fifo_record" if self.imu is not None and self.imu.use_fifo else "sample"])
        return got

    App._sample = metered_sample

    window = App._window

    def metered_window(self, *args):
        before = self.windows
        window(self, *args)
        if self.windows != before:
            _charge("window", costs["window_" + mode])

    App._window = metered_window

    gps = App._gps

    def metered_gps(self):
        before = self.fixes_seen
        got = gps(self)
        if self.fixes_seen != before:
            _charge("gps_fix", costs["gps_fix_" + mode])
        return got

    App._gps = metered_gps

    for name in ("screen_lines", "_diag"):
        _fixed_method(App, name, costs[name.lstrip("_")])

    feed = nmea.Nmea.feed
    per_byte = costs["nmea"][1]

    def metered_feed(self, data):
        accepted = feed(self, data)
        _charge("nmea", per_byte * len(data))
        return accepted

    nmea.Nmea.feed = metered_feed

    if display is not None:
        _meter_display(display.Oled, costs)
    _kernel(app.dr, app.KERNEL, costs)


def _meter_display(Oled, costs):
    show = Oled.show

    def metered_show(self, lines):
        changed = lines != self.lines
        show(self, lines)
        if changed:
            _charge("screen_show", costs["screen_show"])

    Oled.show = metered_show
    page = Oled.step

    def metered_page(self):
        busy = self.busy()
        more = page(self)
        if busy:
            _charge("page", costs["page"])
        return more

    Oled.step = metered_page


def _fixed_method(cls, name, us):
    fn = getattr(cls, name)

    def metered(self, *args):
        result = fn(self, *args)
        _charge(name.lstrip("_"), us)
        return result

    setattr(cls, name, metered)
