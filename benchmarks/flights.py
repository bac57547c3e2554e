"""The long flight the speed and endurance benchmarks fly: the paper's manoeuvre repeated
every minute (multisteps at 2 s and 6 s, elevator pulses at 12 s and 30 s), so the
filters work on real excitation throughout."""

from __future__ import annotations


def repeated_manoeuvre(minutes: int) -> list[str]:
    """Config overrides (`--set` values) for a flight of this many minutes."""
    starts = [m * 60 + s for m in range(minutes) for s in (2.0, 6.0)]
    pulses = [m * 60 + s for m in range(minutes) for s in (12.0, 30.0)]
    return [
        f"simulation.manoeuvre.duration_s={minutes * 60}",
        f"simulation.manoeuvre.multistep_starts_s={starts}",
        f"simulation.manoeuvre.pulse_starts_s={pulses}",
        f"simulation.manoeuvre.pulse_durations_s={[2.0] * len(pulses)}",
        f"simulation.manoeuvre.pulse_amplitudes_deg={[-3.0, 3.0] * minutes}",
    ]
