"""``capvector evaluate``: roll a trained policy out in MuJoCo (robosuite tasks, or LIBERO's suites
under the official protocol) and print a success table."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from json import dumps
from pathlib import Path
from typing import TYPE_CHECKING, Any

from capvector.data.episodes import EpisodeDataset, EvalTask, LiberoEvalTask
from capvector.envs.base import Spec
from capvector.envs.libero.env import LIBERO_TRIALS, Rendering
from capvector.envs.registry import check_specs, suite_of
from capvector.errors import CapVectorError
from capvector.eval.device import Precision, resolve_device, resolve_precision
from capvector.eval.results import SuccessRow, format_success_table, pooled_row, success_rows
from capvector.io.outputs import atomic_write_bytes, check_output
from capvector.module import load_module
from capvector.policy import VLAPolicy
from capvector.tool_cli import run_tool

if TYPE_CHECKING:
    from capvector.eval.rollout import EpisodeResult


def evaluate(
    checkpoint: str,
    tasks: list[EvalTask | LiberoEvalTask],
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
    from capvector.eval.rollout import RolloutEvaluator

    specs = EpisodeDataset(tasks).specs  # an unknown task or variant fails before the load
    torch_device = resolve_device(device)
    precision = resolve_precision(torch_device, precision)  # refused before the load
    module = load_module(checkpoint).eval().to(torch_device)
    spec = module.data_spec
    evaluator = RolloutEvaluator(
        cameras=spec.cameras, image_size=image_size or spec.image_size,
        camera_fovy=spec.camera_fovy, execute_steps=execute_steps, videos=videos,
        video_dir=None if video_dir is None else Path(video_dir), batch_size=batch_size,
        workers=workers,
    )  # fmt: skip
    policy = VLAPolicy(module.backbone, spec, precision)
    return evaluator.run(policy, specs, progress=True)


def main(argv: list[str] | None = None) -> int:
    return run_tool(evaluate_cli, argv, "evaluate")


def evaluate_cli(
    ckpt: str,
    task: Sequence[str] | None = None,
    robot: str = "Panda",
    gripper: str | None = None,
    episodes: int = 20,
    variant: Sequence[str | None] = (None,),
    start_seed: int = EvalTask.start_seed,
    suite: str | None = None,
    tasks: Sequence[int] | None = None,
    trials: int = LIBERO_TRIALS,
    max_steps: int | None = None,
    rendering: Rendering = "auto",
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
) -> None:
    """MuJoCo rollouts of a checkpoint: robosuite tasks, or a LIBERO suite (--suite) under the
    official protocol.

    Args:
        ckpt: Lightning checkpoint or export folder
        task: robosuite task(s) (default Lift)
        gripper: e.g. PandaGripper for IIWA/UR5e/Kinova3/Jaco
        variant: zero-shot scene variants (camera, camera-strong, lighting, color, all, sawyer,
            ur5e); each task is evaluated in each
        start_seed: first evaluation seed
        suite: a LIBERO suite (libero_spatial, libero_object, libero_goal, libero_10,
            libero_90), evaluated as OpenVLA-OFT and openpi do: trial i from the task's official
            initial state i, 10 wait steps, the suite's step limit, LIBERO's success predicate
        tasks: LIBERO task ids (default: every task of the suite)
        trials: LIBERO trials per task, 1..50 (the official protocol runs 50)
        max_steps: step limit of an episode (default: the task's; LIBERO: the suite's)
        rendering: who draws LIBERO's images: auto (the fast renderer where OpenGL runs on the
            CPU, robosuite's on a GPU), fast, or official (LIBERO's own: for policies trained on
            LIBERO's released data)
        from_demos: a folder of LIBERO demos (`capvector demos`): trial i of a task starts where
            its demo i started instead of from official state i, the fixtures placed as they
            were; success from the placements a policy trained on (a diagnostic, not the protocol)
        image_size: render the cameras at this size (default: the policy's; LIBERO's protocol
            renders 256); the backbone resizes to its own input size
        video: folder for mp4s of the first --videos episodes
        batch_size: episodes in flight at once, one batched policy forward for all (1: one at a
            time; default 8, for LIBERO one per usable core: each holds an env of ~1.2 GB)
        workers: processes stepping the simulators (0: this one; default: one per core)
        json: also write the rows as JSON, with every episode's outcome and final proprio
        device: where the policy runs, e.g. cpu, cuda, cuda:1 (default: cuda when there is one)
        precision: 32-true, or bf16-mixed / 16-mixed (autocast; 16-mixed needs a GPU); default
            bf16-mixed on a GPU, 32-true elsewhere
    """
    for what, path in (("--json", json), ("--video", video)):
        if path is not None:  # before minutes of rollouts
            check_output(path, overwrite=True, inputs=[ckpt], what=what)
    eval_tasks = _eval_tasks(
        task, robot, gripper, episodes, variant, start_seed, suite, tasks, trials, max_steps,
        rendering, from_demos,
    )  # fmt: skip
    specs = EpisodeDataset(eval_tasks).specs
    check_specs(specs)  # e.g. every trial's demo is there, before minutes of rollouts
    if batch_size is None:
        batch_size = 8 if suite is None else _libero_batch_size(workers)
    results = evaluate(
        ckpt, eval_tasks, video, videos, execute_steps, batch_size, workers, image_size, device,
        precision,
    )  # fmt: skip
    # success_rows makes a row per (task, robot, variant), in order of appearance: as here
    by_row: dict[tuple[Any, ...], list[tuple[Spec, EpisodeResult]]] = {}
    for s, r in zip(specs, results, strict=True):
        by_row.setdefault((s.task, s.robot, s.variant), []).append((s, r))
    rows = success_rows(results)
    table = rows
    if suite is not None:

        def instruction(row: SuccessRow) -> str | None:
            spec = by_row[row.task, row.robot, row.variant][0][0]
            return suite_of(spec).instruction(spec)

        rows = [dataclasses.replace(row, instruction=instruction(row)) for row in rows]
        table = [*rows, pooled_row(rows, f"{suite} (all)")]
    print(format_success_table(table))
    if json:
        payload = [
            {**row.to_dict(), "per_episode": [
                {**s.describe(), "success": r.success, "steps": r.steps, "reason": r.reason,
                 "final_proprio": r.final_proprio}
                for s, r in by_row[row.task, row.robot, row.variant]
            ]}
            for row in rows
        ]  # fmt: skip
        atomic_write_bytes(json, dumps(payload, indent=2).encode())
    _refuse_non_finite_actions(specs, results)


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
    robot: str,
    gripper: str | None,
    episodes: int,
    variant: Sequence[str | None],
    start_seed: int,
    suite: str | None,
    tasks: Sequence[int] | None,
    trials: int,
    max_steps: int | None,
    rendering: Rendering,
    from_demos: str | None,
) -> list[EvalTask | LiberoEvalTask]:
    """The command line's episodes; options of the other kind of evaluation are refused."""
    if suite is None:
        if tasks is not None or trials != LIBERO_TRIALS or from_demos is not None:
            raise CapVectorError(
                "--tasks, --trials and --from-demos choose LIBERO trials: give --suite too"
            )
        return [
            EvalTask(t, episodes, robot, start_seed, max_steps, gripper, v)
            for t in task or ["Lift"]
            for v in variant
        ]
    robosuite = {"--task": task is not None, "--robot": robot != "Panda",
                 "--gripper": gripper is not None, "--variant": list(variant) != [None]}  # fmt: skip
    if any(robosuite.values()):
        given = ", ".join(name for name, on in robosuite.items() if on)
        raise CapVectorError(
            f"{given} choose robosuite episodes; --suite {suite} runs LIBERO's own scenes: "
            "give one or the other"
        )
    return [
        LiberoEvalTask(
            suite, None if tasks is None else list(tasks), trials, max_steps, rendering, from_demos
        )
    ]


def _libero_batch_size(workers: int | None) -> int:
    """One LIBERO episode per worker: a worker steps its episodes one after the other, so more
    would only hold more envs (~1.2 GB each)."""
    from capvector.eval.rollout import usable_cores

    return max(1, usable_cores() if workers is None else workers)
