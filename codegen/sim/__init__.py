"""Simulator and accuracy benchmark: trajectories with exact truth, MPU-6050 and NEO-6M models, the real-walk
replay, and the outage metrics every position method is measured by.

    trajectory   scenarios static / push / walk / car at 1 kHz truth
    mpu6050      simulate_imu(trajectory, board, seed) -> (t_us, int16 counts (N, 6))
    neo6m        simulate_gps(...) -> GpsTrack; nmea_sentences(track) -> list[bytes]
    replay       the shared real walk, degraded to MPU-6050 quality
    methods      the registry of estimators (seed, const-velocity, hold-last-fix, plug-ins)
    run          build_run / evaluate / format_table
    plot         truth vs estimate in the plane, error against time since GPS loss
    simulate     what `deadreckon simulate` does (the CLI calls it)
    onmicropython  `--on-micropython`: the generated app on the unix-port MicroPython, fed by the models
"""
