"""The fit: perspective probes."""

from __future__ import annotations

import numpy as np
import pytest

from vehicle_pose import RegistrationOptions
from vehicle_pose.registration.fit import probe_factors

from helpers import view

pytestmark = pytest.mark.slow


def test_a_focal_length_outside_the_usual_range_adds_a_probe_to_its_middle(sedan):
    options = RegistrationOptions()
    usual = view(sedan, 60.0, 10.0, focal=1.5 * 640)
    assert probe_factors(usual, options) == list(options.probes.focal_starts)
    for widths in (10.0, 0.4):
        cam = view(sedan, 60.0, 10.0, focal=widths * 640)
        *same, extra = probe_factors(cam, options)
        assert same == list(options.probes.focal_starts)
        assert cam.focal * extra == pytest.approx(np.sqrt(0.7 * 4.0) * 640)
