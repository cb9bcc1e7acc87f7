"""The simulator's consistency measure: an error's squared Mahalanobis distance under the claimed covariance."""

from __future__ import annotations

import pytest

from client_sim.consistency import squared_mahalanobis


def test_squared_mahalanobis_by_hand():
    # C = [[2, 1], [1, 2]]: C⁻¹ = [[2, −1], [−1, 2]] / 3, so d = (1, 1) gives 2/3 and d = (1, −1) gives 2
    assert squared_mahalanobis(1.0, 1.0, [[2.0, 1.0], [1.0, 2.0]]) == pytest.approx(2.0 / 3.0)
    assert squared_mahalanobis(1.0, -1.0, [[2.0, 1.0], [1.0, 2.0]]) == pytest.approx(2.0)
    assert squared_mahalanobis(3.0, 0.0, [[2.25, 0.0], [0.0, 1.0]]) == pytest.approx(4.0)
