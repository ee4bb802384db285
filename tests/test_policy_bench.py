"""`sudd bench policy --quick`: a fresh `small` export, measured; every figure is present and sane."""


from policy.bench import format_table, run_policy_bench
from runtime.bench_runtime import test_cache_dir as cache_dir

CACHE = cache_dir()


def test_bench_quick_returns_its_keys(monkeypatch):
    monkeypatch.setenv("SUDD_CACHE_DIR", str(CACHE))
    f = run_policy_bench(quick=True)
    assert f["preset"] == "small" and (f["sampler"], f["sampler_steps"]) == ("ddim", 8)
    for key in ("chunk", "obs_encoder", "denoise_step", "text_embed", "params", "bytes", "load_ms", "meets_target"):
        assert key in f, key
    for name in ("threads_2", "threads_1", "samples_4", "samples_8"):
        c = f["chunk"][name]
        assert 0 < c["p50_ms"] <= c["p99_ms"] and c["n"] == 20
    assert 2e6 <= f["params"]["obs_encoder"] + f["params"]["denoiser"] <= 6e6
    assert {"obs_encoder.onnx", "denoiser.onnx", "text_encoder.onnx", "stats.npz", "total"} <= set(f["bytes"])
    assert f["bytes"]["total"] < 60e6
    assert "chunk" in format_table(f)


def test_bench_policy_takes_a_bundle_and_only_the_policy_area_does(capsys):
    from runtime.cli import main

    assert main(["bench", "sim", "--quick", "--policy", "policy/bundles/multitask"]) == 2
    assert "--policy BUNDLE is for `sudd bench policy`" in capsys.readouterr().err


def test_bench_times_the_shipped_bundle_with_its_query_inputs():
    # the shipped bundle's obs encoder takes the goal query's release point and the object query's grasp point;
    # the bench once fed only the first and stopped with onnxruntime's missing-input error
    f = run_policy_bench(quick=True, bundle="policy/bundles/multitask")
    assert f["bundle"] == "policy/bundles/multitask" and f["obs_encoder"]["p50_ms"] > 0
    assert 0 < f["chunk"]["threads_2"]["p50_ms"] <= f["chunk"]["threads_2"]["p99_ms"] and "goal_point" in f
