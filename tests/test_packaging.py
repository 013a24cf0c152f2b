"""The packaged Hydra config (conf/ installed as monostixels.conf) works in a non-editable install."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_config_found_in_non_editable_install(tmp_path):
    target = tmp_path / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation",
                    "--target", str(target), str(REPO)], check=True, capture_output=True, timeout=300)
    assert (target / "monostixels" / "conf" / "prior" / "default.yaml").is_file()
    code = ("import monostixels; from monostixels.pipeline import load_config; "
            "c = load_config(['solver.cell_rows=5']); print(monostixels.__file__, c.solver.cell_rows, c.prior.beta_mc)")
    env = {**os.environ, "PYTHONPATH": str(target)}
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    path, rows, beta = out.stdout.split()
    assert path.startswith(str(target)) and rows == "5"
    assert float(beta) > 0
