"""bench/gpu_session.sh: the stages its header documents are the stages it accepts and runs (no GPU needed)."""
import re
import shutil
import subprocess
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "bench" / "gpu_session.sh"
pytestmark = pytest.mark.skipif(shutil.which("bash") is None, reason="needs bash")


def _sets():
    text = SCRIPT.read_text()
    documented = set(re.findall(r"^#   ([a-z0-9]+) ", text, flags=re.M))
    accepted = set(re.search(r"case \$st in ([a-z0-9|]+)\) ;;", text).group(1).split("|"))
    dispatch = text[text.index('for st in $STAGES; do\n    case $st in\n'):]
    ran = set(re.findall(r"^ {8}([a-z0-9]+)\) ", dispatch, flags=re.M))
    return documented, accepted, ran


def test_documented_stages_are_accepted_and_run():
    documented, accepted, ran = _sets()
    assert "srgbwconv" in documented and "conv32k" in documented
    assert documented == accepted == ran


def test_unknown_stage_is_refused_before_anything_is_made(tmp_path):
    out = tmp_path / "out"
    r = subprocess.run(["bash", str(SCRIPT), "lego", str(out), "10", "tests", "nosuchstage"],
                       capture_output=True, text=True, cwd=SCRIPT.parents[1])
    assert r.returncode == 2
    assert r.stdout.strip() == "unknown stage nosuchstage"
    assert not out.exists()
