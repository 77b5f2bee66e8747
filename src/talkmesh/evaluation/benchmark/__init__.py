"""``talkmesh benchmark CONFIG``: train, generate and evaluate every method x seed on one dataset.

The flow, each step resumable (the run can be killed anywhere and started again)::

    load_benchmark(CONFIG)                 validate the config, every recipe and the dataset
    for seed, method (seed-major):         WORK/<method>/seed<seed>/
        for stage in the recipe's stages:  .../<stage>/  train(recipe) with train.seed=<seed>,
                                           train.out_dir=<that dir>, init re-pointed to the
                                           earlier stage's new release, the benchmark's data;
                                           timing.json holds wall time and frames/s
        write_model_predictions            .../pred/    the last stage's release on the test split
        evaluate_dataset x PROTOCOLS       .../scores.json
    baselines (seed-free)                  WORK/baselines/<name>/pred
    ablation (CodeTalker Fig. 7)           WORK/ablation/<cell>/<stage>: stage-1 reconstruction
                                           LVE and codebook usage per grid cell
    speed                                  generation time and real-time factor per method
    report                                 DOCS/<name>.md, DOCS/<name>.json, DOCS/<name>/*.png|mp4

Resume rules: a stage whose ``model.safetensors`` exists is skipped, one with ``last.ckpt`` but no
model is resumed (``train(recipe, resume=True)``), anything else starts afresh. A stage whose
recipe (``recipe.json``, e.g. after an epochs change in the config) or init (the earlier stage's
release, by sha256) changed since it was trained is stale and retrained; predictions are
regenerated when the release they came from changed (``pred/done.json`` keeps its digest).
Completed stages drop their Lightning checkpoints unless ``keep_checkpoints: true`` (hundreds of
MB each; the release is what the benchmark needs).

Aggregates are the mean and the sample standard deviation (ddof=1) over seeds. The paper's ordering
claims (CodeTalker Table 1: LVE CodeTalker < FaceFormer < MeshTalk, VOCA; CodeTalker best in FDD)
are checked between the methods the config names ``codetalker``, ``faceformer``, ``meshtalk`` and
``voca``: a claim holds or is contradicted only when the difference of means exceeds the sum of
the two seed standard deviations, else it is "within seed variance". FDD is compared by its
magnitude (the anchor protocol's FDD is signed).

The package, one module per role: ``config`` (the YAML and the stage plan), ``state`` (what is on
disk), ``steps`` (train, predict, score, time one thing), ``claims`` (aggregates and the papers'
orderings), ``plots`` (figures, video), ``report`` (the markdown page), ``run`` (the whole run).
"""

from talkmesh.evaluation.benchmark.claims import CLAIMS, aggregate, check_claims, mean_std
from talkmesh.evaluation.benchmark.config import (
    BASELINES,
    METRICS,
    AblationSpec,
    BenchmarkConfig,
    Cell,
    DataSpec,
    MethodSpec,
    SpeedSpec,
    StagePlan,
    ablation_cells,
    load_benchmark,
    method_stages,
)
from talkmesh.evaluation.benchmark.plots import draw_on_mesh, sample_indices, save_png
from talkmesh.evaluation.benchmark.report import render_markdown
from talkmesh.evaluation.benchmark.run import BenchmarkResult, plan_lines, run_benchmark
from talkmesh.evaluation.benchmark.state import file_digest, predictions_done, stage_state

__all__ = [
    "BASELINES",
    "CLAIMS",
    "METRICS",
    "AblationSpec",
    "BenchmarkConfig",
    "BenchmarkResult",
    "Cell",
    "DataSpec",
    "MethodSpec",
    "SpeedSpec",
    "StagePlan",
    "ablation_cells",
    "aggregate",
    "check_claims",
    "draw_on_mesh",
    "file_digest",
    "load_benchmark",
    "mean_std",
    "method_stages",
    "plan_lines",
    "predictions_done",
    "render_markdown",
    "run_benchmark",
    "sample_indices",
    "save_png",
    "stage_state",
]
