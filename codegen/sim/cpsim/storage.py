"""Emulated CircuitPython `storage`: remount() of the board's filesystem (the CIRCUITPY drive).

CircuitPython mounts its filesystem read-only to the program while the USB host may write it; boot.py may
remount it writable to the program (the host then sees it read-only). The world's filesystem (simworld's, mounted
at its "mount" path, the app's log folder) stands for the drive: the launcher mounts it read-only before boot.py,
remount("/", readonly=False) makes it writable. After boot.py the firmware refuses a remount while the drive is
visible over USB.
"""

import os

import simworld

_state = {"in_boot": False, "readonly": True}


def _set_readonly(readonly):
    found = simworld.filesystem()
    if found is None:
        return
    disk, mount = found
    os.umount(mount)
    os.mount(os.VfsLfs2(disk), mount, readonly=readonly)  # a new VfsLfs2: a read-only one stays read-only
    _state["readonly"] = readonly


def power_on():
    """The launcher's hook at each boot: the drive is the program's read-only until boot.py remounts it."""
    _set_readonly(True)
    _state["in_boot"] = True


def boot_done():
    _state["in_boot"] = False


def remount(mount_path, readonly=False, *, disable_concurrent_write_protection=False):
    if mount_path != "/":
        raise OSError(19)  # ENODEV: the drive is the only mount
    usb = simworld.scenario().get("circuitpython", {}).get("usb_connected", True)
    if not _state["in_boot"] and usb and not disable_concurrent_write_protection:
        raise RuntimeError("Cannot remount path when visible via USB.")
    _set_readonly(readonly)
    simworld.trace("remount", readonly=readonly)


def getmount(mount_path):
    found = simworld.filesystem()
    if found is None or mount_path != "/":
        raise OSError(22)
    return os.VfsLfs2(found[0])


def readonly():
    return _state["readonly"]
