"""talkmesh-client (web/client) as npm ships it: `npm pack` makes the tarball, npm installs it
offline into a fresh project (three, the peer, from the repository's node_modules), and node
imports every export of the installed package. A module the package reaches outside its folder
is missing from the tarball, so the import fails."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CLIENT = ROOT / "web" / "client"
THREE = ROOT / "node_modules" / "three"

# Every subpath the installed package.json exports, imported by its public name; prints
# {subpath: {export name: typeof}}.
IMPORT_ALL = """
import { readFileSync } from "node:fs";
const pkg = JSON.parse(readFileSync("node_modules/talkmesh-client/package.json", "utf8"));
const subpaths = typeof pkg.exports === "string" ? ["."] : Object.keys(pkg.exports);
const out = {};
for (const sub of subpaths) {
  const module = await import(sub === "." ? pkg.name : pkg.name + sub.slice(1));
  out[sub] = Object.fromEntries(Object.entries(module).map(([k, v]) => [k, typeof v]));
}
console.log(JSON.stringify(out));
"""

# The client on a mesh with Oculus visemes only: the stream's jawOpen reaches viseme_aa.
VISEME_MESH = """
const { TalkmeshClient } = await import(process.argv[1]);
const mesh = {
  isMesh: true, name: "rpm", userData: {},
  morphTargetDictionary: { viseme_sil: 0, viseme_aa: 1, viseme_O: 2 },
  morphTargetInfluences: [0, 0, 0],
};
const scene = { traverse: (f) => f(mesh) };
const client = new TalkmeshClient("ws://127.0.0.1:1/ws/stream", { audioContext: { currentTime: 1 } });
const driven = client.attach(scene);
const names = client.names; // ARKit order until a server's hello says otherwise
const weights = new Float32Array(names.length);
weights[names.indexOf("jawOpen")] = 0.7;
weights[names.indexOf("mouthFunnel")] = 0.4;
client.start = 0;
client.frames.push({ index: 0, time: 0, weights, headPose: null });
client.update();
console.log(JSON.stringify({ driven, influences: mesh.morphTargetInfluences }));
"""


def run(args: list[str], cwd: Path, env: dict[str, str]) -> str:
    done = subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, f"{' '.join(args)} failed:\n{done.stdout}\n{done.stderr}"
    return done.stdout


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> tuple[Path, list[str], dict[str, str]]:
    """A fresh project with the packed talkmesh-client installed from its tarball, offline."""
    npm = shutil.which("npm")
    assert npm, "npm is not installed (make setup)"
    if not THREE.is_dir():
        pytest.fail(f"{THREE} is missing: run `npm ci` in the repo root")
    tmp = tmp_path_factory.mktemp("npm")
    # its own cache, so nothing can come from a cache a network install filled
    env = {
        **os.environ,
        "npm_config_cache": str(tmp / "cache"),
        "npm_config_update_notifier": "false",
    }
    packed = json.loads(
        run([npm, "pack", "--json", "--pack-destination", str(tmp), str(CLIENT)], tmp, env)
    )
    tarball = tmp / packed[0]["filename"]
    project = tmp / "app"
    project.mkdir()
    manifest = {"name": "app", "version": "1.0.0", "private": True, "type": "module"}
    manifest["dependencies"] = {"three": f"file:{THREE}"}  # the peer, as a page brings it
    (project / "package.json").write_text(json.dumps(manifest))
    run([npm, "install", "--offline", "--no-audit", "--no-fund", str(tarball)], project, env)
    return project, [f["path"] for f in packed[0]["files"]], env


def test_the_packed_client_installs_and_every_export_imports(installed):
    project, files, env = installed
    package = project / "node_modules" / "talkmesh-client"
    assert package.is_dir() and not package.is_symlink()  # a copy from the tarball, not a link
    node = shutil.which("node")
    assert node, "node is not installed (make setup)"
    exports = json.loads(run([node, "--input-type=module", "-e", IMPORT_ALL], project, env))
    main = exports["."]
    for name in ("TalkmeshClient", "AvatarRig", "bindAvatar", "openCapture", "parseFrame"):
        assert main.get(name) == "function", (name, main)
    assert main.get("ARKIT_NAMES") == "object"
    assert all(kind != "undefined" for names in exports.values() for kind in names.values()), (
        exports
    )
    assert "README.md" in files and "index.js" in files
    assert not any(f.startswith("example/") for f in files), files  # the page stays in the repo
    peer = json.loads((package / "package.json").read_text())
    assert "three" in peer["peerDependencies"] and "three" not in peer.get("dependencies", {})


def test_the_client_drives_a_viseme_avatar_as_the_viewer_does():
    """The client binds through AvatarRig, so an avatar with Oculus visemes and no ARKit
    targets talks: viseme_aa follows jawOpen, viseme_O mouthFunnel (VISEME_FROM_ARKIT)."""
    node = shutil.which("node")
    assert node, "node is not installed (make setup)"
    url = (CLIENT / "index.js").as_uri()
    done = subprocess.run(
        [node, "--input-type=module", "-e", VISEME_MESH, url],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout)
    assert result["driven"] == 2  # aa and O; sil has no ARKit term and is left alone
    assert result["influences"] == pytest.approx([0.0, 0.7, 0.4])
