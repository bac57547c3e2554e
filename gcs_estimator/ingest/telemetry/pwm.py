"""The servo PWM calibration, both ways: the vehicle encodes with it, the station decodes.

SERVO_OUTPUT_RAW carries microseconds; the [link] table says how they map to the elevator
[rad] (positive trailing edge down) and the throttle [0..1]. Works on scalars and arrays.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, TypeVar

if TYPE_CHECKING:
    import numpy as np
    from numpy.typing import NDArray

    from gcs_estimator.config import LinkConfig

Num = TypeVar("Num", float, "NDArray[np.float64]")


def elevator_pwm(link: LinkConfig, elevator_rad: Num) -> Num:
    """SERVO_OUTPUT_RAW microseconds of an elevator deflection [rad] (unrounded)."""
    return link.elevator_pwm_center_us + elevator_rad * link.elevator_us_per_rad


def elevator_rad(link: LinkConfig, pwm_us: Num) -> Num:
    """Elevator deflection [rad] of a SERVO_OUTPUT_RAW value [us]."""
    return (pwm_us - link.elevator_pwm_center_us) / link.elevator_us_per_rad


def throttle_pwm(link: LinkConfig, throttle: Num) -> Num:
    """SERVO_OUTPUT_RAW microseconds of a throttle setting in [0, 1] (unrounded)."""
    return link.throttle_pwm_min_us + throttle * (
        link.throttle_pwm_max_us - link.throttle_pwm_min_us
    )


def throttle(link: LinkConfig, pwm_us: Num) -> Num:
    """Throttle setting of a SERVO_OUTPUT_RAW value [us]."""
    return (pwm_us - link.throttle_pwm_min_us) / (
        link.throttle_pwm_max_us - link.throttle_pwm_min_us
    )
