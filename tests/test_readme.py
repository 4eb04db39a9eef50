"""The README's Python quick-start runs as written: it extracts XFeat features from the
sample pair, matches them with the shipped ParaFormer and recovers the pair's homography."""
import re
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent


def test_readme_quickstart_runs():
    text = (ROOT / "README.md").read_text()
    start = text.index("## Python quick-start")
    section = text[start:text.index("\n## ", start + 1)]  # other sections' snippets need extras or data
    blocks = re.findall(r"```python\n(.*?)```", section, re.S)
    assert blocks, "README has no python block"
    r = subprocess.run([sys.executable, "-c", "\n".join(blocks)], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    n = int(re.search(r"^(\d+) matches", r.stdout, re.M).group(1))
    inliers = int(re.search(r"^(\d+) inliers", r.stdout, re.M).group(1))
    assert n >= 100 and inliers >= 0.6 * n, r.stdout
    rows = re.findall(r"\[\[?\s*([-\d. ]+)\]", r.stdout)
    h = np.array([[float(v) for v in row.split()] for row in rows[:3]])
    truth = np.loadtxt(ROOT / "assets" / "sample" / "H_0to1.txt")
    np.testing.assert_allclose(h[:2, :2], (truth / truth[2, 2])[:2, :2], atol=0.02)
