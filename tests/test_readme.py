"""The README's commands are executed as written: a user copying them gets what it promises."""

from __future__ import annotations

import re
import shlex
import subprocess
from pathlib import Path

import pytest

from talkmesh.cli import main

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
CLIP = Path(
    "/usr/share/pocketsphinx/test/data/librivox/sense_and_sensibility_01_austen_64kb-0880.wav"
)

pytestmark = pytest.mark.skipif(not CLIP.exists(), reason="pocketsphinx-testdata not installed")


def code_blocks(section: str) -> list[str]:
    text = README.read_text()
    start = text.index(f"## {section}\n")
    end = text.find("\n## ", start + 1)
    return re.findall(r"```[a-z]*\n(.*?)```", text[start : end if end > 0 else None], re.S)


def test_readme_opens_with_the_two_setup_commands():
    """Title, one sentence, then the two set-up commands, before anything else."""
    opening = re.match(r"# talkmesh\n\n([^`#\n][^\n]*)\n\n```\n(.*?)```", README.read_text(), re.S)
    assert opening, "README must open with its title, one sentence, then the set-up code block"
    sentence = opening.group(1)
    assert sentence.endswith(".") and ". " not in sentence, sentence
    commands = [ln.split("#")[0].strip() for ln in opening.group(2).splitlines() if ln.strip()]
    assert commands == ["make demo", "make test"]
    makefile = (ROOT / "Makefile").read_text()
    for target in ("demo", "test", "setup"):
        assert re.search(rf"^{target}:", makefile, re.M), target
    assert "make test" in (ROOT / ".ci" / "run").read_text()


@pytest.fixture
def workdir(tmp_path, monkeypatch) -> Path:
    """The files the README's examples name, made from a real recording."""
    from imageio_ffmpeg import get_ffmpeg_exe

    monkeypatch.chdir(tmp_path)
    (tmp_path / "speech.wav").write_bytes(CLIP.read_bytes())
    (tmp_path / "a.wav").write_bytes(CLIP.read_bytes())
    for name in ("b.flac", "c.mp3"):
        subprocess.run(
            [get_ffmpeg_exe(), "-loglevel", "error", "-i", str(CLIP), str(tmp_path / name)],
            check=True,
        )
    return tmp_path  # my_head.obj: the README's own `talkmesh export-head` writes it


def test_every_cli_example_in_the_readme_runs(workdir):
    block = code_blocks("Use")[
        0
    ]  # the data commands below it write gigabytes: docs/guide/datasets.md has them
    lines = [ln.split("  #")[0].strip() for ln in block.splitlines() if ln.strip()]
    assert len(lines) >= 8
    for line in lines:
        argv = shlex.split(line)
        assert argv[0] == "talkmesh", line
        if argv[1] == "render" and "truth.npz" in argv:  # make the two animations it compares
            for name, seed in (("truth", 1), ("pred", 2)):
                assert (
                    main(["animate", "speech.wav", "--seed", str(seed), "-o", f"{name}.npz", "-q"])
                    == 0
                )
        assert main(argv[1:] + (["-q"] if argv[1] != "info" else [])) == 0, line
        outputs = [argv[k + 1] for k, a in enumerate(argv) if a == "-o"]
        for out in outputs:
            if out.endswith("/"):
                assert sorted(p.name for p in Path(out).iterdir()) == ["a.mp4", "b.mp4", "c.mp4"], (
                    line
                )
            elif out.endswith(".obj") and argv[1] != "export-head":  # an OBJ sequence
                assert list(Path().glob(Path(out).stem + "_*.obj")), line
            else:
                assert Path(out).stat().st_size > 0, line
    from talkmesh.output.formats import load_animation

    assert load_animation("s.npz").vertices.shape[0] == 90


def test_python_example_in_the_readme_runs(workdir):
    (block,) = code_blocks("Python")
    namespace: dict = {}
    exec(compile(block, "README.md", "exec"), namespace)
    anim = namespace["anim"]
    assert anim.vertices.shape[1:] == (anim.num_vertices, 3)
    assert anim.weights.shape == (anim.num_frames, 52)
    assert Path("speech.glb").stat().st_size > 0 and Path("speech.mp4").stat().st_size > 0


def test_docs_speak_of_the_project_not_its_tracker():
    """Documentation describes talkmesh as it is: no issue numbers or review rounds."""
    pages = [README, *sorted((ROOT / "docs").rglob("*.md"))]
    tracker = re.compile(r"\bissues?\s*#?\d+|\bthis round\b|issue's", re.I)
    found = [
        f"{page.relative_to(ROOT)}:{n}: {line.strip()}"
        for page in pages
        for n, line in enumerate(page.read_text().splitlines(), 1)
        if tracker.search(line)
    ]
    assert not found, "\n".join(found)
