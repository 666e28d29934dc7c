"""What the benchmarks print about the machine they ran on."""

from pathlib import Path


def cpu_model() -> str:
    """``lscpu``'s model name and the CPU count, e.g. ``AMD EPYC, 2 CPUs`` (``unknown CPU`` off Linux)."""
    cpuinfo = Path("/proc/cpuinfo")
    if not cpuinfo.exists():
        return "unknown CPU"
    names = [line.split(":", 1)[1].strip() for line in cpuinfo.read_text().splitlines() if line.startswith("model name")]
    return f"{names[0]}, {len(names)} CPUs" if names else "unknown CPU"
