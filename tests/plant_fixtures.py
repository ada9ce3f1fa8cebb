"""Test-only plant models shared by tests/test_plants.py and tests/test_plant_records.py (imported
by file name, with ``tests/`` on the path)."""

from __future__ import annotations

from typing import Any

import numpy as np

from zenswarm.plant.api import QuadrotorModel


class TickCounting(QuadrotorModel):
    """The built-in quadrotor counting its steps: ``self.k`` ticks stepped (0 before the first)."""

    name = "tick-counting"
    description = "the built-in, counting its steps"

    def __init__(self, ctx: Any, params: Any) -> None:
        super().__init__(ctx, params)
        self.k = 0

    def step(self, thrust: np.ndarray, rpy: np.ndarray, disturbance: Any) -> None:
        super().step(thrust, rpy, disturbance)
        self.k += 1
