"""``capvector evaluate``: roll a trained policy out in a registered suite (robosuite tasks, LIBERO's
suites under the official protocol, ...: found by the task set's name) and print a success table."""

from __future__ import annotations

import dataclasses
import sys
from collections.abc import Sequence
from json import dumps
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from capvector.data.episodes import EpisodeDataset, EvalTask
from capvector.envs.base import Spec, check_options
from capvector.envs.registry import check_specs, suite_for_task_set, suite_of
from capvector.errors import CapVectorError
from capvector.eval.device import Precision, resolve_device, resolve_precision
from capvector.eval.results import SuccessRow, format_success_table, pooled_row, success_rows
from capvector.io.names import EVALUATE_PROGRESS
from capvector.io.outputs import atomic_write_bytes, check_output
from capvector.module import load_for_inference
from capvector.policy import VLAPolicy
from capvector.tool_cli import run_tool

if TYPE_CHECKING:
    from capvector.backbones.base import VLABackbone
    from capvector.data.spec import DataSpec
    from capvector.eval.rollout import EpisodeResult, ProgressLines


def evaluate(
    checkpoint: str,
    tasks: list[EvalTask],
    video_dir: str | None = None,
    videos: int = 2,
    execute_steps: int | None = None,
    batch_size: int = 8,
    workers: int | None = None,
    image_size: int | None = None,
    device: str | None = None,
    precision: Precision | None = None,
) -> list[EpisodeResult]:
    """Every episode's result, in the order of ``EpisodeDataset(tasks).specs``. ``batch_size``
    episodes run at once, their simulators in ``workers`` processes (see ``RolloutEvaluator``);
    cameras render at ``image_size`` (default: the policy's own; the backbone resizes what it
    gets to its input size). The policy runs on ``device`` under ``precision`` (defaults: CUDA
    with bf16 autocast when there is a GPU, else the CPU in float32)."""
    EpisodeDataset(tasks)  # an unknown task or variant fails before the load
    torch_device = resolve_device(device)
    precision = resolve_precision(torch_device, precision)  # refused before the load
    # Under autocast a bf16 export runs in bf16 (no float32 copy).
    backbone, spec = load_for_inference(checkpoint, keep_dtype=precision != "32-true")
    return evaluate_backbone(
        backbone.to(torch_device), spec, tasks, video_dir, videos, execute_steps, batch_size,
        workers, image_size, precision,
    )  # fmt: skip


def evaluate_backbone(
    backbone: VLABackbone,
    spec: DataSpec,
    tasks: list[EvalTask],
    video_dir: str | None = None,
    videos: int = 2,
    execute_steps: int | None = None,
    batch_size: int = 8,
    workers: int | None = None,
    image_size: int | None = None,
    precision: Precision = "32-true",
) -> list[EpisodeResult]:
    """The rollouts of ``evaluate`` for a backbone (where its parameters are, in the mode it is in) and
    the data spec it was trained with; a bar on a terminal, else progress lines (a recipe stage's
    log, which ``--status`` reads)."""
    from capvector.eval.rollout import RolloutEvaluator

    specs = EpisodeDataset(tasks).specs
    evaluator = RolloutEvaluator(
        cameras=spec.cameras, image_size=image_size or spec.image_size,
        camera_fovy=spec.camera_fovy, execute_steps=execute_steps, videos=videos,
        video_dir=None if video_dir is None else Path(video_dir), batch_size=batch_size,
        workers=workers,
    )  # fmt: skip
    policy = VLAPolicy(backbone, spec, precision)
    on_terminal = sys.stderr.isatty()
    lines = None if on_terminal else progress_lines(len(specs))
    return evaluator.run(policy, specs, progress=on_terminal, lines=lines)


def progress_lines(episodes: int) -> ProgressLines:
    """``evaluating: 36/100 episodes, 9 succeeded, 44 min, about 78 min left`` on stderr, every 5
    minutes and at the end."""
    from capvector.eval.rollout import ProgressLines

    return ProgressLines(
        episodes, EVALUATE_PROGRESS, lambda line: print(line, file=sys.stderr, flush=True)
    )


def main(argv: list[str] | None = None) -> int:
    return run_tool(evaluate_cli, argv, "evaluate")


Backend = Literal["port", "upstream"]
"""Who simulates a LIBERO suite for ``capvector evaluate``."""


def evaluate_cli(
    ckpt: str,
    task: Sequence[str] | None = None,
    robot: str | None = None,
    gripper: str | None = None,
    episodes: int | None = None,
    variant: Sequence[str | None] = (None,),
    start_seed: int | None = None,
    suite: str | None = None,
    tasks: Sequence[int] | None = None,
    trials: int | None = None,
    max_steps: int | None = None,
    rendering: str | None = None,
    from_demos: str | None = None,
    image_size: int | None = None,
    video: str | None = None,
    videos: int = 2,
    execute_steps: int | None = None,
    batch_size: int | None = None,
    workers: int | None = None,
    json: str | None = None,
    device: str | None = None,
    precision: Precision | None = None,
    backend: Backend = "port",
    upstream_env: str | None = None,
) -> None:
    """Rollouts of a checkpoint in a registered suite: robosuite tasks (--task), or a task set
    (--suite: a LIBERO suite, ...) under its suite's protocol.

    Args:
        ckpt: Lightning checkpoint or export folder
        task: robosuite task(s) (default Lift)
        robot: robosuite arm (default Panda)
        gripper: e.g. PandaGripper for IIWA/UR5e/Kinova3/Jaco
        episodes: episodes of each task (default: the suite's protocol: robosuite 20, LIBERO 50,
            Meta-World 10)
        variant: zero-shot scene variants (camera, camera-strong, lighting, color, all, sawyer,
            ur5e); each task is evaluated in each
        start_seed: first evaluation seed (robosuite, Meta-World; default 1000000)
        suite: a task set of a registered suite instead of --task, e.g. a LIBERO suite
            (libero_spatial, libero_object, libero_goal, libero_10, libero_90), evaluated as
            OpenVLA-OFT and openpi do: trial i from the task's official initial state i, 10 wait
            steps, the suite's step limit, LIBERO's success predicate; or Meta-World's
            metaworld_mt10 / metaworld_mt50, evaluated as LeRobot does (500 steps, corner2)
        tasks: task ids of the set (default: every task of it)
        trials: --episodes, as LIBERO calls them (1..50; the official protocol runs 50)
        max_steps: step limit of an episode (default: the task's; LIBERO: the suite's;
            Meta-World: 500)
        rendering: who draws LIBERO's images: auto (the fast renderer where OpenGL runs on the
            CPU, robosuite's on a GPU), fast, fast-close (the fast one closer to the official
            look), or official (LIBERO's own: for policies trained on LIBERO's released data)
        from_demos: a folder of LIBERO demos (`capvector demos`): trial i of a task starts where
            its demo i started instead of from official state i, the fixtures placed as they
            were; success from the placements a policy trained on (a diagnostic, not the protocol)
        image_size: render the cameras at this size (default: the policy's; LIBERO's protocol
            renders 256); the backbone resizes to its own input size
        video: folder for mp4s of the first --videos episodes
        batch_size: episodes in flight at once, one batched policy forward for all (1: one at a
            time; default 8, for suites whose envs hold gigabytes, LIBERO's ~1.2 GB, one per
            usable core)
        workers: processes stepping the simulators (0: this one; default: one per core)
        json: also write the rows as JSON, with every episode's outcome and final proprio
        device: where the policy runs, e.g. cpu, cuda, cuda:1 (default: cuda when there is one)
        precision: 32-true, or bf16-mixed / 16-mixed (autocast; 16-mixed needs a GPU); default
            bf16-mixed on a GPU, 32-true elsewhere
        backend: who simulates a LIBERO suite: port (this project's LIBERO on robosuite 1.5 and
            MuJoCo 3) or upstream (upstream LIBERO on robosuite 1.4 and MuJoCo 2.3.7, the stack
            of LIBERO's data and published numbers, in its own environment, driving this policy
            through a local `capvector serve`; official rendering)
        upstream_env: the upstream environment's folder (default $CAPVECTOR_LIBERO14, else
            ~/.cache/capvector/libero14, where tools/libero/install_libero14.sh puts it)
    """
    for what, path in (("--json", json), ("--video", video)):
        if path is not None:  # before minutes of rollouts
            check_output(path, overwrite=True, inputs=[ckpt], what=what)
    if backend == "upstream":
        given = dict(
            task=task, robot=robot, gripper=gripper,
            variant=variant if any(v is not None for v in variant) else None,
            start_seed=start_seed, from_demos=from_demos, video=video, batch_size=batch_size,
            workers=workers, rendering=None if rendering == "official" else rendering,
        )  # fmt: skip
        rows = _evaluate_upstream(
            ckpt, suite, tasks, episodes, trials, max_steps, image_size, execute_steps,
            upstream_env, device, precision, given,
        )  # fmt: skip
        _report(rows, suite, json)
        return
    if upstream_env is not None:
        raise CapVectorError(
            "--upstream-env is where --backend upstream runs: add --backend upstream"
        )
    options = dict(
        robot=robot, gripper=gripper, start_seed=start_seed, tasks=tasks, max_steps=max_steps,
        rendering=rendering, from_demos=from_demos,
    )  # fmt: skip
    eval_tasks = _eval_tasks(task, suite, episodes, trials, variant, options)
    specs = EpisodeDataset(eval_tasks).specs
    check_specs(specs)  # e.g. every trial's demo is there, before minutes of rollouts
    if batch_size is None:
        heavy = any(suite_of(s).release_envs for s in specs)
        batch_size = _one_per_worker(workers) if heavy else 8
    results = evaluate(
        ckpt, eval_tasks, video, videos, execute_steps, batch_size, workers, image_size, device,
        precision,
    )  # fmt: skip
    # success_rows makes a row per (task, robot, variant), in order of appearance: as here
    by_row: dict[tuple[Any, ...], list[tuple[Spec, EpisodeResult]]] = {}
    for s, r in zip(specs, results, strict=True):
        by_row.setdefault((s.task, s.robot, s.variant), []).append((s, r))

    def instruction(row: SuccessRow) -> str | None:
        spec = by_row[row.task, row.robot, row.variant][0][0]
        return suite_of(spec).instruction(spec)

    def labelled(row: SuccessRow) -> SuccessRow:
        spec = by_row[row.task, row.robot, row.variant][0][0]
        made_by = suite_of(spec).provenance(spec)
        return dataclasses.replace(
            row, instruction=instruction(row), stack=made_by.stack, renderer=made_by.renderer
        )

    rows = [labelled(row) for row in success_rows(results)]
    episodes_of = {
        (row.task, row.robot, row.variant): [
            {**s.describe(), "success": r.success, "steps": r.steps, "reason": r.reason,
             "final_proprio": r.final_proprio}
            for s, r in by_row[row.task, row.robot, row.variant]
        ]
        for row in rows
    }  # fmt: skip
    _report([(row, episodes_of[row.task, row.robot, row.variant]) for row in rows], suite, json)
    _refuse_non_finite_actions(specs, results)


def _report(
    rows: Sequence[tuple[SuccessRow, list[dict[str, Any]]]], suite: str | None, json: str | None
) -> None:
    """Print the table (a task set of several tasks, --suite, also gets its pooled row) and write
    --json: each row with its episodes (``per_episode``), stack and renderer."""
    table = [row for row, _ in rows]
    print(
        format_success_table(
            table if suite is None else [*table, pooled_row(table, f"{suite} (all)")]
        )
    )
    if json:
        payload = [{**row.to_dict(), "per_episode": episodes} for row, episodes in rows]
        atomic_write_bytes(json, dumps(payload, indent=2).encode())


def _evaluate_upstream(
    ckpt: str,
    suite: str | None,
    tasks: Sequence[int] | None,
    episodes: int | None,
    trials: int | None,
    max_steps: int | None,
    image_size: int | None,
    execute_steps: int | None,
    upstream_env: str | None,
    device: str | None,
    precision: Precision | None,
    given: dict[str, Any],
) -> list[tuple[SuccessRow, list[dict[str, Any]]]]:
    """``--backend upstream``: the flags it cannot honour refused, the environment found (or the
    command that installs it named) before the checkpoint loads, then the rows."""
    from capvector.workflows.evaluate_upstream import evaluate_upstream, upstream_python

    unsupported = [_flag(k) for k, v in given.items() if v is not None]
    if unsupported:
        raise CapVectorError(
            f"--backend upstream runs LIBERO's protocol as upstream does and does not take "
            f"{', '.join(unsupported)}: drop it, or use --backend port"
        )
    if suite is None or suite_for_task_set(suite).name != "libero":
        raise CapVectorError(
            f"--backend upstream evaluates a LIBERO suite (--suite libero_spatial, ...), got "
            f"{'--suite ' + suite if suite else 'no --suite'}"
        )
    if episodes is not None and trials is not None:
        raise CapVectorError("--episodes and --trials are the same: give one")
    count = trials or episodes or suite_for_task_set(suite).eval_episodes
    options = {k: v for k, v in (("tasks", tasks), ("max_steps", max_steps)) if v is not None}
    # Bad tasks or trials refused here.
    episodes = len(EpisodeDataset([EvalTask(suite, count, "libero", options)]).specs)
    upstream_python(upstream_env)  # refused before the load
    rows = evaluate_upstream(
        ckpt, suite, tasks, count, max_steps=max_steps, image_size=image_size,
        execute_steps=execute_steps, upstream_env=upstream_env, device=device,
        precision=precision, lines=progress_lines(episodes),
    )  # fmt: skip
    return [(SuccessRow.from_dict(row), row["per_episode"]) for row in rows]


NON_FINITE = "non-finite action"
"""How an episode that the policy answered with NaN or inf ends (``Episode.execute``)."""


def _refuse_non_finite_actions(specs: Sequence[Spec], results: Sequence[EpisodeResult]) -> None:
    """A policy that answers NaN is broken, not unsuccessful: after the table (and --json),
    say so and exit non-zero rather than report a success rate of 0 as if it had tried."""
    broken = [(s, r) for s, r in zip(specs, results, strict=True) if NON_FINITE in (r.reason or "")]
    if broken:
        spec, result = broken[0]
        raise CapVectorError(
            f"{len(broken)} of {len(results)} episodes ended on a non-finite action from the "
            f"policy (e.g. {spec.task} seed {spec.seed}: {result.reason}): its weights or "
            "preprocessing produce NaN/inf; check the checkpoint before trusting these numbers"
        )


def _eval_tasks(
    task: Sequence[str] | None,
    suite: str | None,
    episodes: int | None,
    trials: int | None,
    variant: Sequence[str | None],
    options: dict[str, Any],
) -> list[EvalTask]:
    """The command line's episodes: each task set (``--task``s, or ``--suite``) in each variant,
    with the options given; an option the set's suite does not take is refused by its flag."""
    if task is not None and suite is not None:
        raise CapVectorError(
            f"--task names a task, --suite {suite} a task set: give one or the other"
        )
    if episodes is not None and trials is not None:
        raise CapVectorError("--episodes and --trials are the same: give one")
    given = {k: v for k, v in options.items() if v is not None}
    out = []
    for name in [suite] if suite is not None else task or ["Lift"]:
        owner = suite_for_task_set(name)
        for v in variant:
            own = given if v is None else {**given, "variant": v}
            check_options(owner.specs, own, f"{name} ({owner.name})", _flag)
            count = episodes or trials or owner.eval_episodes
            out.append(EvalTask(name, count, owner.name, own))
    return out


def _flag(option: str) -> str:
    return "--" + option.replace("_", "-")


def _one_per_worker(workers: int | None) -> int:
    """One episode per worker for suites whose envs hold gigabytes (``Suite.release_envs``): a
    worker steps its episodes one after the other, so more would only hold more envs."""
    from capvector.eval.rollout import usable_cores

    return max(1, usable_cores() if workers is None else workers)
