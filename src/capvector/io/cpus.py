"""How many CPUs this process may actually use: its affinity mask and its cgroup's CPU quota.

``os.cpu_count()`` counts the machine's cores, whatever a SLURM allocation (``--cpus-per-task``
pins the job's affinity, or caps its cgroup), a container's CPU limit or ``taskset`` leave to the
process, so workers sized by it oversubscribe the cores the process has.
"""

from __future__ import annotations

import math
import os
from pathlib import Path


def usable_cpus(root: Path = Path("/")) -> int:
    """The CPUs this process may run on (``os.sched_getaffinity``), at most its cgroup's CPU quota
    (rounded up; cgroup v2 ``cpu.max`` or v1 ``cpu.cfs_quota_us``, of its cgroup or a parent).
    ``root``: where ``/proc`` and ``/sys`` are read from."""
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    quota = cgroup_cpu_quota(root)
    return max(1, min(cpus or 1, math.ceil(quota) if quota is not None else cpus or 1))


def cgroup_cpu_quota(root: Path = Path("/")) -> float | None:
    """The smallest CPU quota (in CPUs) on the way from this process's cgroup up to its
    hierarchy's mount point; None when there is none or no cgroup filesystem to read."""
    try:
        memberships = (root / "proc/self/cgroup").read_text().splitlines()
        mounts = (root / "proc/self/mountinfo").read_text().splitlines()
    except OSError:
        return None
    quotas = []
    for line in memberships:
        _, controllers, path = line.split(":", 2)
        version = 2 if controllers == "" else 1 if "cpu" in controllers.split(",") else None
        mount = _mount_point(mounts, version) if version else None
        if mount is None:
            continue
        mount_point, mount_root = root / mount[0].lstrip("/"), mount[1]
        relative = os.path.relpath(path, mount_root) if path.startswith(mount_root) else "."
        folder = (mount_point / relative).resolve()
        while True:
            quotas.append(_quota(folder, version))
            if folder == mount_point.resolve() or folder.parent == folder:
                break
            folder = folder.parent
    found = [q for q in quotas if q is not None]
    return min(found) if found else None


def _mount_point(mounts: list[str], version: int) -> tuple[str, str] | None:
    """(mount point, root inside the hierarchy) of the cgroup v2 hierarchy, or of v1's ``cpu``."""
    for line in mounts:
        fields = line.split()
        separator = fields.index("-")
        fs_type, options = fields[separator + 1], fields[separator + 3].split(",")
        if (version == 2 and fs_type == "cgroup2") or (
            version == 1 and fs_type == "cgroup" and "cpu" in options
        ):
            return fields[4], fields[3]
    return None


def _quota(folder: Path, version: int) -> float | None:
    try:
        if version == 2:
            limit, period = (folder / "cpu.max").read_text().split()
            return None if limit == "max" else int(limit) / int(period)
        limit = int((folder / "cpu.cfs_quota_us").read_text())
        period = int((folder / "cpu.cfs_period_us").read_text())
        return None if limit < 0 else limit / period
    except (OSError, ValueError):
        return None
