"""benchmarks/suite_cpu.py: a test that computes is counted as CPU, one that sleeps as wait."""

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

TESTS = '''
import time

def test_busy():
    end = time.process_time() + 0.4
    while time.process_time() < end:
        pass

def test_sleeps():
    time.sleep(0.4)
'''


@pytest.mark.slow
def test_cpu_and_wait_per_test_and_module(tmp_path):
    (tmp_path / "test_two.py").write_text(TESTS)
    proc = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "suite_cpu.py"), "--",
                           "-p", "no:cacheprovider", "-q", str(tmp_path / "test_two.py")],
                          capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    rows = {ln.split()[0].split("::")[-1]: [float(v) for v in ln.split()[1:]]
            for ln in proc.stdout.splitlines() if "test_two.py::" in ln}
    cpu, wall, wait = rows["test_sleeps"]
    assert wait >= 0.3 and cpu < 0.2, rows
    # the busy test waited least, so it may be listed or not; the module row holds both
    module = [ln.split() for ln in proc.stdout.splitlines()
              if ln.split() and ln.split()[0].endswith("test_two.py")]
    assert module, proc.stdout
    n, mcpu, mwall, mwait = module[0][1:]
    assert int(n) == 2 and float(mcpu) >= 0.35 and float(mwall) >= 0.75, module
    assert "2 tests:" in proc.stdout and "pytest exit 0" in proc.stdout


def test_a_run_with_no_tests_is_one_line_and_fails(tmp_path):
    (tmp_path / "test_none.py").write_text("x = 1\n")
    proc = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "suite_cpu.py"), "--",
                           "-p", "no:cacheprovider", "-q", str(tmp_path / "test_none.py")],
                          capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert proc.returncode != 0
    assert proc.stderr.strip().splitlines()[-1].startswith("suite_cpu: pytest ran no test")
