"""plasticity.volume: the rest volume held (keep) or moved toward the target's (target), by at most
volume_rate a frame from the plasticity's first frame, the same at every frame whatever came
before (a resumed run follows it); the volume warning names the setting."""

import math

import pytest

from physmorph.meshes.fit import volume_mismatch
from physmorph.settings.plasticity import PlasticityConfig


@pytest.mark.parametrize("ratio", [0.58, 1.7])
def test_the_rest_volume_moves_toward_the_target_by_at_most_the_rate(ratio):
    cfg = PlasticityConfig(volume="target", volume_rate=0.05, start_frame=2)
    path = [cfg.rest_volume_ratio(k, ratio) for k in range(0, 40)]
    assert path[0] == path[1] == 1.0  # before the plasticity's first frame
    steps = [b / a for a, b in zip(path, path[1:])]
    assert all(1 / 1.05 - 1e-12 <= s <= 1.05 + 1e-12 for s in steps)
    assert path[2] == pytest.approx(1.05 ** math.copysign(1, math.log(ratio)))
    reached = next(k for k, r in enumerate(path) if r == pytest.approx(ratio))
    assert reached == 2 + math.ceil(abs(math.log(ratio)) / math.log(1.05)) - 1
    assert all(r == pytest.approx(ratio) for r in path[reached:])  # and stays there
    # keep holds the source's volume at every frame
    assert {PlasticityConfig(volume="keep").rest_volume_ratio(k, ratio) for k in range(40)} == {1.0}


def test_the_volume_warning_names_the_setting():
    keep = volume_mismatch("iso_bunny", 1170.0, 675.0, 15.0, volume_setting="keep")
    assert "plasticity.volume: target" in keep and "a target size of 18.0 (now 15)" in keep
    target = volume_mismatch("iso_bunny", 1170.0, 675.0, 15.0, volume_setting="target")
    assert target.startswith("iso_bunny: the target holds 58 % of the source's volume")
    assert "moves the body's rest volume there" in target and "cannot fill" not in target
    # a run without plasticity has no such setting to name
    assert "plasticity.volume" not in volume_mismatch("iso_bunny", 1170.0, 675.0, 15.0)
