"""The README's Python quick-start runs as written and prints matches."""
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_readme_quickstart_runs():
    blocks = re.findall(r"```python\n(.*?)```", (ROOT / "README.md").read_text(), re.S)
    assert blocks, "README has no python block"
    r = subprocess.run([sys.executable, "-c", "\n".join(blocks)], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    n = int(re.search(r"^(\d+) matches$", r.stdout, re.M).group(1))
    assert 0 < n <= 40, r.stdout
    assert "paraformer.Matcher(model='paraformer'" in r.stdout
