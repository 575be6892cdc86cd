"""`links bench generate --lean`'s profile: every sample of a shard's writing charged to one
stage, the compiled search the largest (it is most of the work:
tests/engine/kinematics/test_sampling.py and the benchmarks page)."""

from __future__ import annotations

from links_ray.bench.generate import format_generate
from links_ray.bench.shard_profile import OTHER, STAGES, profile_shard


def test_a_shards_time_is_charged_to_its_stages() -> None:
    profile = profile_shard(topologies=260, seed=3)
    assert profile["topologies"] == 260 and profile["mechanisms"] == 1300
    shares = profile["shares"]
    assert list(shares) == [stage for stage, _ in STAGES] + [OTHER]
    assert profile["samples"] >= 20 and abs(sum(shares.values()) - 1) < 1e-9
    assert max(shares, key=shares.get) == "position search (compiled sampler and simulation)"
    text = format_generate(
        {
            "tables": ["mechanisms"],
            "runs": [],
            "valid_per_core_second": 7000.0,
            "target_valid_per_core_second": 8000,
            "profile": profile,
        }
    )
    assert "(target 8,000)" in text and "position search" in text
