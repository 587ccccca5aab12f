"""`deadreckon simulate` options out of their range: refused before the simulation starts (so no run that cannot
finish, no numpy warning, no table of nan), naming the option, with a hint; --plot never writes anything but a
new or replaced regular .png file. Each case through the CLI: exit 2, no traceback, within the bound, nothing
written around the working folder."""

from __future__ import annotations

import pytest

from hostilekit import assert_refused, run_cli, snapshot, user_files

CASES = [
    ("step-zero", ["--step", "0"], ["--step 0: the time between outage starts is between 1 and 3600 seconds"]),
    ("step-negative", ["--step", "-5"], ["--step -5:"]),
    ("step-nan", ["--step", "nan"], ["--step nan:"]),
    ("step-tiny-hang", ["--step", "1e-4"], ["--step 0.0001:"]),
    ("step-inf", ["--step", "inf"], ["--step inf:"]),
    ("seed-negative", ["--seed", "-1"], ["--seed -1: a seed is a whole number from 0 to 4294967295"]),
    ("seed-2**100", ["--seed", str(2**100)], [f"--seed {2**100}:"]),
    ("outage-inf", ["--outage", "inf"], ["--outage inf: an outage is a positive number of seconds"]),
    ("outage-nan", ["--outage", "nan"], ["--outage nan:"]),
    ("plot-dev-full", ["--plot", "/dev/full"], ["--plot /dev/full: the plot is a PNG image"]),
    ("plot-existing-folder", ["--plot", "projects"], ["--plot projects: the plot is a PNG image"]),
    ("plot-folder-named-png", ["--plot", "shots.png"], ["--plot shots.png: exists and is not a regular file"]),
    ("plot-link-named-png", ["--plot", "notes.png"], ["--plot notes.png: exists and is not a regular file"]),
    ("plot-txt", ["--plot", "plot.txt"], ["--plot plot.txt: the plot is a PNG image", "hint: e.g. --plot plot.png"]),
    ("plot-missing-folder", ["--plot", "nowhere/walk.png"], ["the folder nowhere does not exist"]),
]


@pytest.mark.parametrize("options,phrases", [case[1:] for case in CASES], ids=[case[0] for case in CASES])
def test_simulate_option_out_of_range_is_refused(tmp_path, options, phrases):
    home = tmp_path / "home"
    home.mkdir()
    user_files(home)
    (home / "shots.png").mkdir()
    (home / "notes.png").symlink_to("notes.txt")
    before = snapshot(home)
    outcome = run_cli("simulate", *options, cwd=home)
    assert_refused(outcome, *phrases, "hint: ")
    assert snapshot(home) == before
