"""Simulator and accuracy benchmark: trajectories with exact truth, MPU-6050 and NEO-6M models, the real-walk
replay, and the outage metrics every position method is measured by.

    trajectory   scenarios at 1 kHz truth: static, push, walk (in a hand, a pocket, a backpack), bike, car, a car
                 in town (car parks, queues, idling stands), a walker who stands holding the device
    features     |f|'s shaking and its share above 8 Hz per window, alike for simulated and recorded streams
    vibration    what shakes a carried device: road roughness through a suspension, potholes, an engine
    mpu6050      simulate_imu(trajectory, board, seed) -> (t_us, int16 counts (N, 6))
    neo6m        simulate_gps(...) -> GpsTrack; nmea_sentences(track) -> list[bytes]
    replay       the shared real walk, degraded to MPU-6050 quality
    methods      the registry of estimators (seed, fused, const-velocity, hold-last-fix)
    run          build_run / evaluate / format_table (+ bootstrap intervals); the tuning and reported seeds
    plot         truth vs estimate in the plane, error against time since GPS loss
    simulate     what `deadreckon simulate` does (the CLI calls it)
    harness, mpsim/  the emulated board the generated app runs on (unix-port MicroPython)
    onmicropython  `--on-micropython`: the generated app on the emulated board, fed by the models
"""

# The scenario names, here so that the CLI can offer them without importing NumPy.
SIMULATED = ("static", "push", "walk", "walk-pocket", "walk-backpack", "bike", "car", "car-town", "walk-stand")
SCENARIOS = SIMULATED + ("replay-walk",)
