"""The installed package finds its kernels and scenes wherever it runs from."""

import json
import subprocess
import sys
from pathlib import Path

REPO_KERNELS = Path(__file__).resolve().parent.parent / "kernels"


def test_installed_package_finds_every_kernel_and_scene(tmp_path):
    # -I: isolated mode, so clothbench comes from the installed distribution (the wheel in
    # CI), not from the checkout in the current directory
    kernels = sorted(
        p.name for p in REPO_KERNELS.iterdir() if p.suffix in {".cl", ".cu", ".frag", ".vert", ".comp", ".glsl", ".h"}
    )
    assert kernels, "kernels/ holds no kernel sources"
    code = (
        "import json, sys\n"
        "from clothbench.kernel_source import read_kernel\n"
        "from clothbench.model.scene import builtin_scenes, load_scene\n"
        "names = json.loads(sys.argv[1])\n"
        "print(json.dumps({'kernels': {n: len(read_kernel(n)) for n in names},\n"
        "                  'scenes': [load_scene(s).name for s in builtin_scenes()]}))\n"
    )
    out = subprocess.run(
        [sys.executable, "-I", "-c", code, json.dumps(kernels)],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 0, out.stderr
    found = json.loads(out.stdout)
    for name in kernels:
        assert found["kernels"][name] == len((REPO_KERNELS / name).read_text()), name
    assert {"sphere", "drape", "cylinder", "curtain"} <= set(found["scenes"])
