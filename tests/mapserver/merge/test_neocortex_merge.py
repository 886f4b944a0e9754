"""sdr-htm maps are not merge candidates yet (issue 17 part 5 not done): refused with the reason."""

from __future__ import annotations

from core.config import preset
from mapserver.merge.snapshot import params_incompatibility


def test_sdr_maps_are_refused_with_a_reason_and_lvc_maps_still_merge() -> None:
    assert params_incompatibility(preset("poseidon"), preset("poseidon")) is None  # must still merge
    assert "front-ends differ" in (params_incompatibility(preset("poseidon"), preset("poseidon-sdr")) or "")
    assert "not merged yet" in (params_incompatibility(preset("poseidon-sdr"), preset("poseidon-sdr")) or "")
