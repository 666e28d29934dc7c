"""
The ``thesis`` preset's update against the thesis code's numbers for one fixed batch, without the thesis code: the
numbers (losses, the latents fed to the critics, the targets' outputs, the multiplier's step and each parameter's
clipped gradient norm) are in tests/data/thesis_update_reference.json, written only by
``benchmarks/tools/reference_parity.py --ref-dir DIR --write-fixture`` from a run of tsmir/ds-slac.
"""

import json
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
FIXTURE = REPO / "tests" / "data" / "thesis_update_reference.json"


def test_the_thesis_update_gives_the_thesis_codes_numbers(monkeypatch) -> None:
    monkeypatch.syspath_prepend(str(REPO / "benchmarks" / "tools"))
    import reference_parity as parity

    reference = json.loads(FIXTURE.read_text())["numbers"]
    model = parity.build_model(parity.THESIS)
    parity.fixed_weights(model)
    latent_batch, batch = parity.fixed_batches(model, parity.THESIS)
    ours = parity.fingerprint(parity.run_ours(model, latent_batch, batch, actor_noise=[]))

    assert set(ours) == set(reference), set(ours) ^ set(reference)
    apart = [
        f"{key}: thesis code {reference[key]:.7g}, here {ours[key]:.7g}"
        for key in reference
        if ours[key] != pytest.approx(reference[key], rel=parity.TOLERANCE, abs=1e-8)
    ]
    assert not apart, f"the thesis preset's update drifted from the thesis code's ({len(apart)} of {len(ours)}): " + "; ".join(
        apart
    )
