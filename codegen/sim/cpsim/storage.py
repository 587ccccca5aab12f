"""Emulated CircuitPython `storage`: remount() of the board's filesystem (the CIRCUITPY drive).

CircuitPython mounts its filesystem read-only to the program while the USB host may write it; boot.py may
remount it writable to the program (the host then sees it read-only). The world's filesystem (simworld's, mounted
at its "mount" path, the app's log folder) stands for the drive: the launcher mounts it read-only before boot.py,
remount("/", readonly=False) makes it writable. After boot.py the firmware refuses a remount while the drive is
visible over USB. The drive is FAT (512-byte sectors), as on every CircuitPython board: the firmware has no LittleFS.
"""

import os

import simworld

_state = {"in_boot": False, "readonly": True}
_EROFS = 30


class _Drive:
    """The drive as the program sees it: the FAT filesystem, refusing (OSError EROFS) to open a file for writing,
    remove, rename or make a folder while it is read-only to the program, as CircuitPython's vfs_fat does
    (verify_fs_writable). Its unix port leaves that to the board's supervisor, which is this."""

    def __init__(self, fat):
        self.fat = fat

    def _writable(self):
        if _state["readonly"]:
            raise OSError(_EROFS)

    def mount(self, readonly, mkfs):
        self.fat.mount(False, mkfs)

    def umount(self):
        self.fat.umount()

    def open(self, path, mode):
        if "w" in mode or "a" in mode or "+" in mode or "x" in mode:
            self._writable()
        return self.fat.open(path, mode)

    def remove(self, path):
        self._writable()
        return self.fat.remove(path)

    def rename(self, old, new):
        self._writable()
        return self.fat.rename(old, new)

    def mkdir(self, path):
        self._writable()
        return self.fat.mkdir(path)

    def rmdir(self, path):
        self._writable()
        return self.fat.rmdir(path)

    def ilistdir(self, path):
        return self.fat.ilistdir(path)

    def stat(self, path):
        return self.fat.stat(path)

    def statvfs(self, path):
        return self.fat.statvfs(path)

    def chdir(self, path):
        return self.fat.chdir(path)

    def getcwd(self):
        return self.fat.getcwd()

    @property
    def readonly(self):
        return _state["readonly"]


_drive = [None]


def _set_readonly(readonly):
    found = simworld.filesystem()
    if found is None:
        return
    disk, mount = found
    _state["readonly"] = readonly
    if _drive[0] is None:
        os.umount(mount)
        _drive[0] = _Drive(simworld.filesystem_class()(disk))
        os.mount(_drive[0], mount)


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
    return _drive[0]


def readonly():
    return _state["readonly"]
