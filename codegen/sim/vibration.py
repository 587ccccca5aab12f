"""What shakes a device that rides on something: road roughness through a suspension, an engine, a pedalling rider.

The motion scripts of codegen.sim.trajectory give smooth paths; a real vehicle adds vibration that an IMU sees
far above the accelerations that move it. The models here turn speed and distance into vibration displacements and
angles on the 1 kHz truth grid, so the truth stays exact (positions, velocities, accelerations and body rates of
the trajectory include the vibration; nothing is added to the sensor alone).

Road (ISO 8608:2016): the road's height along each wheel track is a random profile with displacement PSD
Gd(n) = Gd(n0) (n / n0)^-2, n0 = 0.1 cycle/m; class A roads (very good) have Gd(n0) up to 32e-6 m^3, class B
(good) 32..128e-6 m^3 (geometric means 16e-6 and 64e-6). A slope that is white noise along the road has exactly this
PSD. Each track is felt by the front wheel and, one wheelbase later, by the rear one; left and right tracks are
independent.

Suspension: the two-mass quarter-car (sprung body mass, unsprung wheel mass, spring, damper, tyre stiffness; the
classic model of vehicle-dynamics texts, e.g. Gillespie, Fundamentals of Vehicle Dynamics, ch. 5). The passenger
car's parameters put the body mode at ~1.3 Hz and wheel hop at ~11 Hz, the textbook ranges. The four corners' body
heights give heave, pitch (front - rear over the wheelbase) and roll (left - right over the track width). Through
this model a class A..B road at 10-15 m/s gives 0.025-0.06 g rms of vertical body acceleration; a real
roof-mounted drive measured 0.048 g (median standard deviation of |f| while driving), which the bundled figures are
checked against (tests/test_sim_vibration.py).

Potholes: depressions of a few centimetres over tens of centimetres in one wheel track, a Poisson process along the
road; through the quarter-car they give the sharp, sometimes range-saturating, jolts of a real drive.

Engine: a four-stroke, four-cylinder engine shakes at its firing frequency (twice the crankshaft rate) and its
harmonics; idle at 750-850 rpm (25-28 Hz), driving at 1300-2600 rpm through a five-speed gearbox. The angular
amplitude is chosen so that the rate at idle is 0.7-1.0 degree/s rms, as measured on the real drive at
its stops; the linear amplitude (0.1 m/s^2 rms at idle) is our choice: small enough that a car at rest with its
engine running is "almost" at rest, which is exactly the case rest detection has to decide.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import bilinear, lfilter, lfilter_zi

from codegen.board.model import STANDARD_GRAVITY

ISO8608_N0 = 0.1  # cycle/m, reference spatial frequency
ISO8608_CLASS_GD = {"A": 16e-6, "B": 64e-6, "C": 256e-6}  # m^3, geometric mean Gd(n0) per class


@dataclass(frozen=True)
class QuarterCar:
    """One corner of a vehicle: sprung mass on a spring and damper over an unsprung mass on a tyre."""

    sprung_kg: float = 350.0
    unsprung_kg: float = 40.0
    spring_n_m: float = 22_000.0
    damper_ns_m: float = 1_800.0
    tyre_n_m: float = 200_000.0

    def transfer(self) -> tuple[np.ndarray, np.ndarray]:
        """Continuous transfer function road height -> body height, (numerator, denominator) in s."""
        ms, mu, k, c, kt = self.sprung_kg, self.unsprung_kg, self.spring_n_m, self.damper_ns_m, self.tyre_n_m
        coupling = np.array([c, k])
        num = kt * coupling
        den = np.polysub(np.polymul([ms, c, k], [mu, c, k + kt]), np.pad(np.polymul(coupling, coupling), (2, 0)))
        return num, den

    def wheel_transfer(self) -> tuple[np.ndarray, np.ndarray]:
        """Continuous transfer function road height -> wheel (unsprung mass) height."""
        ms, c, k, kt = self.sprung_kg, self.damper_ns_m, self.spring_n_m, self.tyre_n_m
        return kt * np.array([ms, c, k]), self.transfer()[1]

    def body_height(self, road: np.ndarray, rate_hz: float) -> np.ndarray:
        """Body height (m) for road heights (m) sampled at rate_hz along axis 0, from steady state."""
        return self._filter(self.transfer(), road, rate_hz)

    def wheel_height(self, road: np.ndarray, rate_hz: float) -> np.ndarray:
        """Wheel (unsprung mass) height (m) for road heights (m), as body_height."""
        return self._filter(self.wheel_transfer(), road, rate_hz)

    @staticmethod
    def _filter(transfer, road: np.ndarray, rate_hz: float) -> np.ndarray:
        num, den = transfer
        b, a = bilinear(num, den, fs=rate_hz)
        zi = lfilter_zi(b, a)
        zi = zi[:, None] * road[:1] if road.ndim == 2 else zi * road[0]
        out, _ = lfilter(b, a, road, axis=0, zi=zi)
        return out


@dataclass(frozen=True)
class Road:
    """Road roughness (ISO 8608) and potholes for one drive."""

    gd_n0: float = 40e-6  # m^3, between class A and B
    potholes_per_km: float = 2.5
    pothole_depth_m: tuple[float, float] = (0.02, 0.05)
    pothole_length_m: tuple[float, float] = (0.3, 0.9)
    longest_wave_m: float = 50.0  # longer waves are the grade, modelled by the trajectory itself
    contact_m: float = 0.15  # m, the tyre's contact length: it bridges shorter bumps (the tyre's enveloping)


def road_profile(length_m: float, road: Road, rng: np.random.Generator, tracks: int = 2, dx: float = 0.02,
                 bumps=()):
    """Heights (m) of `tracks` wheel tracks every dx metres over length_m, with potholes and `bumps` (speed bumps
    across the whole road: (centre m, height m, length m) each, a raised cosine), as a tyre feels them (averaged
    over its contact length); returns (x, (K, tracks))."""
    k = int(np.ceil(length_m / dx)) + 2
    x = np.arange(k) * dx
    # a white slope of one-sided PSD (2 pi n0)^2 Gd(n0) gives heights with Gd(n) = Gd(n0) (n / n0)^-2
    slope_psd = (2 * np.pi * ISO8608_N0) ** 2 * road.gd_n0
    slope = rng.standard_normal((k, tracks)) * np.sqrt(slope_psd / (2 * dx))
    heights = np.cumsum(slope, axis=0) * dx
    # remove wavelengths beyond longest_wave_m (a first-order high-pass along the road)
    alpha = np.exp(-2 * np.pi * dx / road.longest_wave_m)
    trend = lfilter([1 - alpha], [1, -alpha], heights, axis=0, zi=heights[:1] * alpha)[0]
    heights = heights - trend
    for _ in range(rng.poisson(road.potholes_per_km * length_m / 1000.0)):
        where = rng.uniform(0.0, length_m)
        track = rng.integers(tracks)
        depth = rng.uniform(*road.pothole_depth_m)
        span = rng.uniform(*road.pothole_length_m)
        inside = np.abs(x - where) < span / 2
        heights[inside, track] -= depth * 0.5 * (1 + np.cos(2 * np.pi * (x[inside] - where) / span))
    for where, height, span in bumps:
        inside = np.abs(x - where) < span / 2
        heights[inside] += (height * 0.5 * (1 + np.cos(2 * np.pi * (x[inside] - where) / span)))[:, None]
    m = max(1, int(round(road.contact_m / dx)))  # the tyre bridges bumps shorter than its contact length
    padded = np.concatenate([np.repeat(heights[:1], m, axis=0), heights], axis=0)
    total = np.cumsum(padded, axis=0)
    return x, (total[m:] - total[:-m]) / m


@dataclass(frozen=True)
class Engine:
    """A four-stroke engine's shake at the firing frequency (cylinders / 2 per crankshaft turn) and harmonics."""

    cylinders: int = 4
    idle_rpm: float = 800.0
    shift_up_rpm: float = 2600.0
    gear_ratios: tuple[float, ...] = (13.5, 8.2, 5.7, 4.4, 3.6)  # overall (gearbox x final drive)
    wheel_radius_m: float = 0.31
    rate_rms_dps: float = 0.95  # angular rate at idle, rms, degree/s, before the DLPF (the real drive: 0.7-1.0 after)
    accel_rms_ms2: float = 0.1  # linear acceleration at idle, rms, m/s^2
    harmonics: tuple[float, ...] = (1.0, 0.35, 0.15)  # relative amplitudes of the 1st, 2nd, 3rd firing orders
    vertical: bool = False  # the linear shake along Up (an inline four's free force at the firing frequency is
    # vertical), instead of a random direction per order

    def rpm(self, speed: np.ndarray) -> np.ndarray:
        """Crankshaft speed for a road speed (m/s): the highest gear that keeps the engine above 1.6 x idle (a
        driver's upshift), capped at shift_up_rpm; below that in first gear, never below idle (the clutch slips)."""
        wheel_rpm = np.asarray(speed, dtype=float) / (2 * np.pi * self.wheel_radius_m) * 60.0
        out = np.maximum(wheel_rpm * self.gear_ratios[0], self.idle_rpm)
        chosen = np.zeros(np.shape(out), dtype=bool)
        for ratio in reversed(self.gear_ratios):  # top gear first: the lowest rpm that is above 1.6 x idle
            rpm = wheel_rpm * ratio
            use = ~chosen & (rpm >= 1.6 * self.idle_rpm)
            out[use] = rpm[use]
            chosen |= use
        return np.minimum(out, self.shift_up_rpm)


def engine_shake(t: np.ndarray, rpm: np.ndarray, running: np.ndarray, engine: Engine, rng: np.random.Generator):
    """Angles (n, 3) rad and displacements (n, 3) m of the engine's shake felt by the body, with their exact
    derivatives (rates rad/s, velocities m/s): sums of firing-order sinusoids with random fixed directions.
    `running` scales the amplitude (booleans, or 0..1 for an engine spinning up: its own derivative is left out)."""
    n = len(t)
    dt = t[1] - t[0]
    firing_hz = rpm / 60.0 * engine.cylinders / 2.0
    phase = 2 * np.pi * np.cumsum(firing_hz) * dt
    angles = np.zeros((n, 3))
    rates = np.zeros((n, 3))
    disp = np.zeros((n, 3))
    vel = np.zeros((n, 3))
    norm = np.sqrt(np.sum(np.square(engine.harmonics)) / 2.0)  # rms of the unit-amplitude sum
    on = running.astype(float)
    for order, weight in enumerate(engine.harmonics, start=1):
        axis_w = rng.normal(size=3)
        axis_w /= np.linalg.norm(axis_w)
        axis_a = rng.normal(size=3)
        axis_a = np.array([0.0, 0.0, 1.0]) if engine.vertical else axis_a / np.linalg.norm(axis_a)
        offset = rng.uniform(0, 2 * np.pi)
        omega = 2 * np.pi * firing_hz * order  # rad/s
        wave, dwave = np.sin(order * phase + offset), np.cos(order * phase + offset)
        # rate amplitude r: angle = r/omega sin, rate = r cos; acceleration amplitude a: disp = -a/omega^2 sin
        r = np.radians(engine.rate_rms_dps) * weight / norm
        a = engine.accel_rms_ms2 * weight / norm
        angles += (on * r / omega * wave)[:, None] * axis_w
        rates += (on * r * dwave)[:, None] * axis_w
        disp += (-on * a / omega**2 * wave)[:, None] * axis_a
        vel += (-on * a / omega * dwave)[:, None] * axis_a
    return angles, rates, disp, vel


@dataclass(frozen=True)
class VehicleBody:
    wheelbase_m: float = 2.6
    track_m: float = 1.5
    corner: QuarterCar = QuarterCar()
    harshness: float = 0.0  # share of the wheels' own motion that reaches the cabin past the spring and damper
    # (through the suspension's rubber bushings and top mounts: the wheel hop a real cabin feels)


def road_shake(distance: np.ndarray, rate_hz: float, body: VehicleBody, road: Road, rng: np.random.Generator,
               bumps=()):
    """Heave (m), pitch and roll (rad, in the sense of trajectory.euler_to_matrix for a vehicle whose x axis points
    forwards and y left: pitch positive nose down, roll positive right side down) of the body for the distance
    travelled at each truth sample (m, non-decreasing), from both tracks (left, right) under front and rear wheels;
    `bumps` as road_profile's."""
    x, heights = road_profile(float(distance[-1]) + body.wheelbase_m + 1.0, road, rng, tracks=2, bumps=bumps)
    front = distance + body.wheelbase_m
    corners = np.stack([np.interp(front, x, heights[:, 0]), np.interp(front, x, heights[:, 1]),
                        np.interp(distance, x, heights[:, 0]), np.interp(distance, x, heights[:, 1])], axis=-1)
    z = body.corner.body_height(corners, rate_hz)  # (n, 4): front-left, front-right, rear-left, rear-right
    if body.harshness > 0.0:
        z = z + body.harshness * (body.corner.wheel_height(corners, rate_hz) - z)  # the bushings' deflection
    heave = z.mean(axis=1)
    pitch = ((z[:, 2] + z[:, 3]) - (z[:, 0] + z[:, 1])) / (2 * body.wheelbase_m)
    roll = ((z[:, 0] + z[:, 2]) - (z[:, 1] + z[:, 3])) / (2 * body.track_m)
    return heave, pitch, roll


def window_std_of_norm(f: np.ndarray, rate_hz: float, window_s: float = 1.0) -> np.ndarray:
    """Standard deviation of |f| in consecutive windows of window_s, in g (the statistic the vehicle goal quotes)."""
    m = int(round(window_s * rate_hz))
    norm = np.linalg.norm(f, axis=1) / STANDARD_GRAVITY
    k = len(norm) // m
    return norm[: k * m].reshape(k, m).std(axis=1)
