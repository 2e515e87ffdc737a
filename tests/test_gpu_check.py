"""The GPU check's scripts (docs/gpu.md) cannot rot silently: they parse, the profiler script still finds
the trainer names it drives, and the report reads a check's logs. Nothing here needs a GPU."""

import importlib.util
import json
import shutil
import subprocess
from pathlib import Path

import pytest

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"


def _load(name: str):
    spec = importlib.util.spec_from_file_location(name, SCRIPTS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("script", ["gpu-prepare", "gpu-check"])
def test_the_shell_scripts_parse(script):
    if shutil.which("bash") is None:
        pytest.skip("no bash")
    proc = subprocess.run(["bash", "-n", str(SCRIPTS / script)], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr


def test_the_profiler_script_imports_and_parses_its_arguments(capsys):
    profile = _load("gpu_profile")  # imports Trainer, late_iteration, count_step_ops, normalize_spec
    assert callable(profile.Trainer.setup) and callable(profile.Trainer.step)
    with pytest.raises(SystemExit) as exc:
        profile.main(["--help"])
    assert exc.value.code == 0 and "--device" in capsys.readouterr().out
    args = profile.parser().parse_args(["data/subject", "--size", "256", "--device", "cpu", "--json", "p.json"])
    assert (args.data, args.size, args.device, args.json, args.profiled) == ("data/subject", 256, "cpu", "p.json", 10)


def test_the_report_reads_what_is_there_and_nulls_the_rest(tmp_path, capsys):
    logs = tmp_path / "logs"
    logs.mkdir()
    (logs / "steps.tsv").write_text("install\t0\t1.5\t120\ntests\t1\t80.2\t200\ntrain\t124\t150.0\t150\n"
                                    "profile\tskipped\t0\t4\nbench_render\tinterrupted\t\t\n")
    (logs / "settings.tsv").write_text("DEVICE\tcuda\nSIZE\t512\nITERS\t3000\n")
    (logs / "nvidia-smi.txt").write_text("NVIDIA H100 80GB HBM3, 580.159.04, 81559 MiB\n")
    (logs / "tests.log").write_text("..F.s\nFAILED tests/test_render.py::test_gsplat_matches_cpu - assert\n"
                                    "1 failed, 27 passed, 1 skipped, 621 deselected in 50.21s\n")
    (logs / "train.log").write_text("train: 50%\r\ndone: 3000 iterations in 55 s (54.55 it/s), 64000 Gaussians, "
                                    "last training PSNR 36.10 dB; checkpoint run/checkpoints/last.pt\n")
    (logs / "mem.csv").write_text("512\n7000\n6900\n")
    (logs / "eval_test.json").write_text(json.dumps({"mean": {"psnr": 37.7, "ssim": 0.98, "lpips": 0.02},
                                                     "frames": [{}] * 30}))
    (logs / "bench_render.json").write_text(json.dumps({"fps": 142.0, "frame_s": 0.007, "size": 1080}))
    (logs / "eval_novel_pose.json").write_text("{not json")
    report = _load("gpu_check_report")
    assert report.main([str(logs), str(tmp_path / "gpu-check.json")]) == 0
    r = json.loads((tmp_path / "gpu-check.json").read_text())
    assert r["gpu"] == {"name": "NVIDIA H100 80GB HBM3", "driver": "580.159.04", "memory_total": "81559 MiB"}
    assert r["steps"]["train"] == {"rc": 124, "seconds": 150.0, "limit_s": 150}
    assert r["steps"]["profile"]["rc"] == "skipped" and r["steps"]["bench_render"]["rc"] == "interrupted"
    assert r["tests"]["passed"] == 27 and r["tests"]["failed"] == 1
    assert r["tests"]["failed_tests"] == ["tests/test_render.py::test_gsplat_matches_cpu"]
    assert r["train"]["iterations"] == 3000 and r["train"]["gaussians"] == 64000
    assert r["train_gpu_memory"] == {"idle_mib": 512, "peak_mib": 7000, "samples": 3}
    assert r["eval_test"]["psnr"] == 37.7 and r["eval_test"]["frames"] == 30
    assert r["eval_novel_pose"] is None and r["bench_step"] is None and r["profile"] is None
    assert r["bench_render"]["fps"] == 142.0 and r["bench_render"]["frame_ms"] == 7.0
    out = capsys.readouterr().out
    assert "NVIDIA H100" in out and "train rc=124" in out and "142 FPS" in out
