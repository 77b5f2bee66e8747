"""Animate a library of speech files: each worker holds the head and the model, loaded once (for
forked local workers, once before they fork), then takes file after file, the longest first; a
file whose outputs all exist is done and skipped; a file that fails is reported in its summary
row and the batch goes on.

Workers are local processes (``workers``) or Ray actors (:mod:`talkmesh.batch.cluster`); either
way they run :class:`Animator`, so a file gives the same outputs wherever it is animated.
"""

from __future__ import annotations

import os
import sys
import time
import warnings
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

from talkmesh.audio.loading import SOUNDFILE_EXTENSIONS, audio_duration
from talkmesh.errors import TalkmeshError, os_error_message
from talkmesh.face.corrections import BILABIAL, GAIN, LIP_CLOSURE, MIX, PAUSE_SOURCE
from talkmesh.face.head_motion import NATURAL
from talkmesh.face.performance import Performance
from talkmesh.output import VIDEO_SIZE

OK, SKIPPED, FAILED = "ok", "skipped", "failed"
COMPRESSED_BYTES_PER_S = 16_000  # 128 kbit/s: a common mp3/m4a rate, to order files by length


@dataclass(frozen=True)
class AnimateSettings:
    """What every file of a batch is animated with (the options of ``talkmesh animate``).

    ``model`` is ``procedural``, a bundled model's name or a release file; ``identity`` or
    ``template`` picks the face; ``avatar`` makes .glb/.vrm outputs copies of that character;
    ``head`` is a plain head mesh the bundled head's motion is carried onto
    (:meth:`talkmesh.face.rig.Rig.carry_blocks`), in its own units and axes.
    """

    model: str = "procedural"
    identity: str | None = None
    template: str | None = None
    avatar: str | None = None
    head: str | None = None
    text: str | None = None
    fps: float | None = None  # None: the model's own (30 for the procedural animator)
    seed: int = 0
    style_mix: dict[str, float] | None = field(default=None, hash=False)
    blinks: bool = True
    pause_gate: bool = True
    lip_closure: bool = LIP_CLOSURE
    procedural_mix: float = MIX
    loudness_gain: float = GAIN
    bilabial_closure: bool = BILABIAL
    pause_source: str = PAUSE_SOURCE
    performance: Performance | None = field(default=None, hash=False)  # None: neutral
    head_motion: float = NATURAL  # 0: the head still
    int8: str | None = None
    runtime: str = "auto"  # torch, onnxruntime or auto (talkmesh.models.runtime)
    size: int = VIDEO_SIZE
    camera: str = "front"
    overwrite: bool = False
    triangles: bool = True  # False: every output is .npy/.npz, a template needs no triangles
    normalize_template: bool = False  # normalise a BIWI-topology template as prepare-biwi does


class Job(NamedTuple):
    """One speech file and the outputs still to write for it."""

    audio: Path
    outputs: tuple[Path, ...]


class Row(NamedTuple):
    """One line of the summary: the speech file, its length (s), the frames written, the wall
    time it took (s), ``ok`` / ``skipped`` (outputs already there) / ``failed``, and the error;
    ``note`` is said on the terminal only (the share of the motion ARKit weights solved from
    another topology miss)."""

    file: str
    duration: float | None
    frames: int | None
    seconds: float
    status: str
    error: str = ""
    note: str = ""


class Animator:
    """What one worker holds: the face and the model, loaded once; called once per file.

    ``threads`` caps torch's threads, so that workers sharing a machine do not fight over it.
    """

    def __init__(self, settings: AnimateSettings, threads: int | None = None):
        from talkmesh.face.assets import load_head

        self.settings = settings
        s = settings
        self.head = face_for(s) if s.template else load_head(s.identity)
        self.rig = None
        if s.head is not None:
            from talkmesh.face.rig_files import load_rig

            self.rig = load_rig(s.head)
        self.model: object = s.model
        self.int8 = s.int8
        if s.model != "procedural":
            from talkmesh.models.runtime import open_model

            self.model = open_model(s.model, s.runtime, int8=s.int8, threads=threads)
            self.int8 = None
        if threads is not None:  # after the model: torch's threads if it runs on torch
            _set_threads(threads)

    def __call__(self, job: Job) -> Row:
        """Animate ``job`` into its outputs; its row, failed or not. A warning shown meanwhile
        names the file (:func:`warnings_about`)."""
        start = time.perf_counter()
        with warnings_about(str(job.audio)):
            return self._animate(job, start)

    def _animate(self, job: Job, start: float) -> Row:
        from talkmesh.face.solve import Residual
        from talkmesh.output import VIDEO_SUFFIXES, write_animation
        from talkmesh.output.avatar import AVATAR_SUFFIXES
        from talkmesh.output.streaming import WEIGHT_SUFFIXES, save_blocks
        from talkmesh.pipeline import animate_blocks

        s = self.settings
        try:
            anim = animate_blocks(
                job.audio,
                head=self.head,
                text=s.text,
                fps=s.fps,
                seed=s.seed,
                model=self.model,
                style_mix=s.style_mix,
                blinks=s.blinks,
                pause_gate=s.pause_gate,
                lip_closure=s.lip_closure,
                procedural_mix=s.procedural_mix,
                loudness_gain=s.loudness_gain,
                bilabial_closure=s.bilabial_closure,
                pause_source=s.pause_source,
                int8=self.int8,
                performance=s.performance,
                head_motion=s.head_motion,
            )
            # .npz and .npy stream as frames are made; the other formats get the whole animation
            rigged = [
                p
                for p in job.outputs
                if s.avatar is not None and p.suffix.lower() in AVATAR_SUFFIXES
            ]
            # a user's head: files in its own units and axes, videos seen from its front; an
            # avatar's videos show the avatar
            videos = [
                p
                for p in job.outputs
                if (self.rig is not None or s.avatar is not None)
                and p.suffix.lower() in VIDEO_SUFFIXES
            ]
            plain = [p for p in job.outputs if p not in rigged and p not in videos]
            residual = None
            if not self.head.rigged and (
                rigged or any(p.suffix.lower() in WEIGHT_SUFFIXES for p in plain)
            ):
                residual = Residual()  # ARKit weights of another topology, solved
                anim = self._solver().solve_blocks(anim, residual)
            if self.rig is not None:
                anim = self.rig.carry_blocks(anim, self.head.template)
            whole = save_blocks(
                anim,
                plain,
                overwrite=s.overwrite,
                size=s.size,
                camera=s.camera,
                keep=bool(rigged or videos),
            )
            for p in rigged:
                write_avatar(whole, Path(s.avatar), p, s.overwrite)
            for p in videos:
                if s.avatar is not None:
                    write_avatar_video(whole, Path(s.avatar), p, s)
                    continue
                facing = self.rig.facing(whole)
                write_animation(facing, p, overwrite=s.overwrite, size=s.size, camera=s.camera)
        except TalkmeshError as e:
            return _failed(job, start, str(e))
        except OSError as e:  # e.g. the input went away: this file's failure, not the batch's
            return _failed(job, start, os_error_message(e, action="use"))
        except Exception as e:  # a bug on one file must not stop a library of thousands
            return _failed(job, start, f"internal error: {type(e).__name__}: {e}")
        seconds = time.perf_counter() - start
        note = "" if residual is None else f"ARKit weights miss {residual.share:.1%} of the motion"
        return Row(
            str(job.audio), anim.num_frames / anim.fps, anim.num_frames, seconds, OK, "", note
        )

    def _solver(self):
        """The ARKit solve of the template's topology (rigged once per mesh and process)."""
        from talkmesh.face.solve import solver_for_mesh

        name = f"{self.settings.template} ({self.head.name})"
        return solver_for_mesh(self.head.template, self.head.faces, name)


@contextmanager
def warnings_about(name: str) -> Iterator[None]:
    """Warnings shown within say which input they are about: ``name: message`` (unless the
    message names it already), so that a batch's warnings can be told apart."""
    previous = warnings.showwarning

    def show(message, category, filename, lineno, file=None, line=None):
        text = str(message)
        previous(
            text if name in text else f"{name}: {text}", category, filename, lineno, file, line
        )

    warnings.showwarning = show
    try:
        yield
    finally:
        warnings.showwarning = previous


def write_avatar(anim, avatar: Path, path: Path, overwrite: bool) -> None:
    """``anim``'s ARKit weights as the animation clip of a copy of ``avatar`` at ``path``."""
    from talkmesh.face.arkit import to_arkit_order
    from talkmesh.output.avatar import animate_avatar

    weights = to_arkit_order(anim.weights, anim.weight_names)
    animate_avatar(
        avatar,
        weights,
        anim.fps,
        path,
        overwrite=overwrite,
        head_pose=anim.head_pose,
        phones=anim.phones,
    )


def write_avatar_video(anim, avatar: Path, path: Path, s: AnimateSettings) -> None:
    """A video of ``avatar`` itself playing ``anim``'s clip (as :func:`write_avatar` would write
    it), with the speech."""
    from talkmesh.face.arkit import to_arkit_order
    from talkmesh.output.atomic import writing
    from talkmesh.output.avatar import talking_scene
    from talkmesh.output.render import render_avatar_video

    scene = talking_scene(
        avatar,
        to_arkit_order(anim.weights, anim.weight_names),
        anim.fps,
        head_pose=anim.head_pose,
        phones=anim.phones,
    )
    with writing(path):
        if path.exists() and not s.overwrite:
            raise TalkmeshError(f"{path} already exists: choose another -o or pass --overwrite")
        path.parent.mkdir(parents=True, exist_ok=True)
        render_avatar_video(
            scene,
            path,
            s.size,
            audio=anim.audio,
            sample_rate=anim.sample_rate,
            audio_file=anim.audio_file,
            inputs=[avatar],
            camera=s.camera,
        )


def _failed(job: Job, start: float, message: str) -> Row:
    message = message.strip().splitlines()[0] if message.strip() else "failed"
    if str(job.audio) not in message:
        message = f"{job.audio}: {message}"
    return Row(str(job.audio), None, None, time.perf_counter() - start, FAILED, message)


def _set_threads(threads: int) -> None:
    """PyTorch's threads and the BLAS/OpenMP pools numpy and scipy loaded (OpenBLAS starts one
    thread per core in every forked worker: two workers on two cores then ran four spinning
    BLAS threads and took 43% more CPU than one worker for the same files)."""
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(max(1, threads))
    except ImportError:  # an optional speed-up: without it only PyTorch's threads are set
        pass
    torch = sys.modules.get("torch")  # not imported for a model on ONNX Runtime
    if torch is not None:
        torch.set_num_threads(max(1, threads))


def plan_jobs(
    audio: list[Path], outputs: list[list[Path]], overwrite: bool
) -> tuple[list[Job], list[Row]]:
    """The files still to animate (with the outputs they lack) and the rows of those done.

    Without ``overwrite``, a file whose outputs all exist is done; one with some of them (a
    batch stopped between two formats) writes only the missing ones. Outputs are renamed into
    place complete, so an existing output is never a partial one.
    """
    jobs: list[Job] = []
    done: list[Row] = []
    for a, paths in zip(audio, outputs):
        todo = tuple(paths) if overwrite else tuple(p for p in paths if not p.exists())
        if todo:
            jobs.append(Job(a, todo))
        else:
            done.append(Row(str(a), None, None, 0.0, SKIPPED))
    return jobs, done


def run_local(jobs: list[Job], settings: AnimateSettings, workers: int = 1) -> Iterator[Row]:
    """Animate ``jobs`` in this process (``workers`` 1) or in that many processes, each with its
    own :class:`Animator` and an equal share of the cores; rows come in the order files finish.

    Several workers take the longest files first (:func:`longest_first`), so that they finish
    together rather than one animating a long file while the others wait. Where processes fork,
    the model is loaded once here and the workers share it (copy-on-write) instead of each
    loading it again.
    """
    global _PRELOADED
    if not jobs:  # every file done: no model to load (a resumed batch's quick no-op)
        return
    if workers <= 1 or len(jobs) <= 1:
        animator = Animator(settings)
        for job in jobs:
            yield animator(job)
        return
    import multiprocessing

    threads = max(1, usable_cpus() // workers)
    # fork where there is one: workers start with talkmesh, torch and pocketsphinx already
    # imported (spawn re-imports them in every worker: seconds of CPU each, measured in
    # bench/batch_throughput.py); torch resets its CPU thread pool in forked children
    methods = multiprocessing.get_all_start_methods()
    ctx = multiprocessing.get_context("fork" if "fork" in methods else "spawn")
    if ctx.get_start_method() == "fork":
        _PRELOADED = _preload(settings)
    pool = ProcessPoolExecutor(
        max_workers=min(workers, len(jobs)),
        mp_context=ctx,
        initializer=_start_worker,
        initargs=(settings, threads, os.getpid()),
    )
    try:
        futures = {pool.submit(_work, job): job for job in longest_first(jobs)}
        _PRELOADED = None  # the workers have forked with it: this process needs it no more
        for future in as_completed(futures):
            job = futures[future]
            try:
                yield future.result()
            except BrokenProcessPool:
                message = (
                    f"{job.audio}: a worker process died (out of memory?): rerun the batch "
                    "to resume, with fewer --workers"
                )
                yield Row(str(job.audio), None, None, 0.0, FAILED, message)
    except BaseException:  # Ctrl-C, SIGTERM (SystemExit), a closed generator: stop the workers
        stop_workers(pool)
        raise
    finally:
        _PRELOADED = None
        pool.shutdown(wait=True, cancel_futures=True)


def stop_workers(pool: ProcessPoolExecutor) -> None:
    """End ``pool``'s workers now, mid-file (their outputs are temporaries, cleared by the next
    run): ``shutdown`` alone would let each finish the file it is on."""
    pool.shutdown(wait=False, cancel_futures=True)
    for process in list((getattr(pool, "_processes", None) or {}).values()):
        if process.is_alive():
            process.terminate()


def longest_first(jobs: list[Job]) -> list[Job]:
    """``jobs`` from the longest audio to the shortest, ties in the given order: workers that
    take the longest file left finish within about one short file of each other (LPT
    scheduling), where in the given order a long file last keeps one worker busy while the
    others idle. Lengths come from the headers of the files libsndfile reads; other files (mp3,
    m4a: probing each would start an ffmpeg) count by size at ``COMPRESSED_BYTES_PER_S``; a file
    that cannot be read counts as 0 s (it fails fast)."""

    def seconds(job: Job) -> float:
        try:
            if job.audio.suffix.lower() in SOUNDFILE_EXTENSIONS:
                return audio_duration(job.audio)
            return job.audio.stat().st_size / COMPRESSED_BYTES_PER_S
        except (TalkmeshError, OSError):
            return 0.0

    durations = [seconds(j) for j in jobs]
    order = sorted(range(len(jobs)), key=lambda k: -durations[k])
    return [jobs[k] for k in order]


def _preload(settings: AnimateSettings) -> Animator | None:
    """The :class:`Animator` the forked workers inherit (None when it cannot be made here: each
    worker then makes its own and reports why on its files). Loaded with one thread, so that
    this process starts no OpenMP thread team, which a forked child cannot use."""
    try:
        import torch
    except ImportError:
        torch = None
    before = torch.get_num_threads() if torch is not None else None
    try:
        if torch is not None:
            torch.set_num_threads(1)
        return Animator(settings)
    except Exception:
        return None
    finally:
        if torch is not None:
            torch.set_num_threads(before)


def usable_cpus() -> int:
    """The CPUs this process may run on (its affinity, e.g. under taskset), else all of them."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # macOS, Windows
        return os.cpu_count() or 1


# The worker process's own Animator (or why it could not be made), set by _start_worker.
_ANIMATOR: Animator | str | None = None
# The Animator loaded before the workers fork (run_local), which they take as their own.
_PRELOADED: Animator | None = None


def _start_worker(settings: AnimateSettings, threads: int, parent: int) -> None:
    global _ANIMATOR
    die_with_parent(parent)
    try:
        if _PRELOADED is not None and _PRELOADED.settings == settings:
            _set_threads(threads)
            _ANIMATOR = _PRELOADED
            return
        _ANIMATOR = Animator(settings, threads)
    except Exception as e:  # reported on every file it was given, instead of a dead pool
        _ANIMATOR = str(e) or type(e).__name__


PARENT_POLL_S = 1.0  # how often a worker checks that the batch that started it is alive


def die_with_parent(parent: int) -> None:
    """Make this worker process end when ``parent`` (the batch's process) does, however it
    ends: ``kill -9``, SIGTERM from ``timeout``, systemd or ``docker stop``. The kernel sends
    SIGKILL when the parent dies (Linux's PR_SET_PDEATHSIG); elsewhere, and as a second net, a
    thread checks the parent's pid every PARENT_POLL_S. SIGTERM and SIGINT get their default
    actions back: the parent's handlers are for the parent (a SystemExit raised in a worker
    would be sent back as a job's result and the worker would go on)."""
    import signal
    import sys
    import threading

    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    if sys.platform.startswith("linux"):
        try:
            import ctypes

            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(1, signal.SIGKILL, 0, 0, 0)  # PR_SET_PDEATHSIG = 1
        except (OSError, AttributeError):
            pass
    if os.getppid() != parent:  # the parent died before the line above
        os._exit(1)

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(PARENT_POLL_S)
        os._exit(1)

    threading.Thread(target=watch, name="talkmesh-parent-watch", daemon=True).start()


def _work(job: Job) -> Row:
    if not isinstance(_ANIMATOR, Animator):
        return _failed(job, time.perf_counter(), f"the worker could not start: {_ANIMATOR}")
    return _ANIMATOR(job)


def check_settings(settings: AnimateSettings) -> None:
    """Fail on a missing model, face or avatar once, before any worker starts."""
    from talkmesh.face.assets import load_head

    if settings.template:
        face_for(settings)
    else:
        load_head(settings.identity)
    if settings.head:
        from talkmesh.face.rig_files import load_rig

        load_rig(settings.head)
    if settings.model != "procedural":
        from talkmesh.models.bundled import resolve

        resolve(settings.model)  # the file only: torch is imported by the workers that run it


def face_for(settings):
    """``settings.template`` on any topology (:mod:`talkmesh.datasets.templates`): a
    templates.pkl without :SUBJECT takes the subject the style mix names alone."""
    from talkmesh.datasets.templates import load_face_template

    mix = settings.style_mix
    alone = next(iter(mix)) if mix and len(mix) == 1 else None
    return load_face_template(
        settings.template,
        subject=alone,
        triangles=settings.triangles,
        normalize=settings.normalize_template,
    )
