"""SIGTERM during `formation train` saves a checkpoint and exits 130, as Ctrl-C does."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path


def test_sigterm_saves_a_checkpoint_then_exits(tmp_path):
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "formation.cli", "train", "configs/smoke.yaml", "--out", str(out),
           "--set", "train.total_env_steps=1000000", "--set", "checkpoint.every_iterations=1"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        deadline = time.monotonic() + 240
        while not (out / "checkpoint").is_dir():  # training is under way: a periodic checkpoint exists
            assert proc.poll() is None and time.monotonic() < deadline, "training did not start"
            time.sleep(0.5)
        time.sleep(2)
        signalled = time.time()
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130
    assert "stopped: checkpoint saved" in err and "Traceback" not in err
    assert Path(out / "checkpoint" / "algorithm_state.pkl").stat().st_mtime >= signalled - 1
