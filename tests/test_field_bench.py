"""The per-sample field benchmark of ``garmentnerf bench`` (``perf/field_bench.py``)."""

from garmentnerf.perf.field_bench import bundled_field_configs, field_benchmark


def linear(n_in: int, n_out: int) -> int:
    return n_in * n_out + n_out


def test_field_benchmark_times_both_fields_at_the_bundled_sizes():
    out = field_benchmark(samples=2048, rounds=1)
    assert out["samples"] == 2048
    paper, uvh = bundled_field_configs().values()
    # The paper's M_NeRF, counted by hand: [b_o, h, f^d, f^s] (20) -> 4 x 128 -> density, zeta (64).
    assert out["paper"]["parameters"] == (linear(20, 128) + 3 * linear(128, 128) + linear(128, 1)
                                          + linear(128, paper.appearance_dim))
    # The uvh field: three 16-channel planes (256 x 256, 64 x 256 twice) and a 2 x 64 head on
    # [f^s (8), planes (48), f^d (8), direction (3), PE(h) (9)].
    planes = 16 * (256 * 256 + 2 * 64 * 256)
    assert out["uvh"]["parameters"] == (planes + linear(76, 64) + linear(64, 64) + linear(64, 1)
                                        + linear(64, uvh.appearance_dim))
    for name in ("paper", "uvh"):
        row = out[name]
        for mode in ("render", "train"):
            assert row[f"{mode}_us_per_sample"] > 0
            assert abs(row[f"{mode}_samples_per_s"] * row[f"{mode}_us_per_sample"] - 1e6) < 1e-3
