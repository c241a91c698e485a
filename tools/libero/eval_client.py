"""LIBERO's evaluation on upstream LIBERO (robosuite 1.4) driving a served policy, as openpi runs
its LIBERO example: `capvector serve` answers, this client steps the simulator.

Runs in the environment `tools/libero/install_libero14.sh` makes (robosuite 1.4 cannot share one
with this project's 1.5; it imports LIBERO and openpi-client only, nothing of capvector's)::

    capvector serve --ckpt runs/libero/export --port 8000                        # here
    MUJOCO_GL=egl ~/.cache/capvector/libero14/bin/python tools/libero/eval_client.py \\
        --port 8000 --suite libero_spatial --tasks 0 1 --trials 3 --json client.json   # there

The protocol follows openpi's `examples/libero/main.py` (written anew here, not copied): per task
an `OffScreenRenderEnv`; trial i resets, loads the task's initial state i and sends 10 wait steps
`[0, 0, 0, 0, 0, 0, -1]`; then up to the suite's step limit, each request carries both images
rotated 180°, the 8-d state (eef position, axis-angle, gripper joints) and the instruction under
openpi's keys, and the first `--replan-steps` actions of the answer run before the next request;
success is LIBERO's `done` after a step. Where it differs, so that the two evaluations of a policy,
this one and `capvector evaluate --suite` on our robosuite 1.5 port, differ only by the simulator:

- Images are rendered at the served policy's `image_size` (its metadata) and sent as rendered;
  openpi renders 256 px and pads-and-resizes to 224 (`--image-size 256` renders LIBERO's size).
  `capvector evaluate` renders at the policy's size too.
- Actions run as the metadata says: the whole chunk (`action_horizon`), as `capvector evaluate`
  does by default (openpi's default re-plans every 5: `--replan-steps 5`).
- The gripper command is binarised (> 0 closes, else opens), as `capvector evaluate` and
  OpenVLA-OFT do; openpi's client sends the policy's value as is.
- Fixtures (stove, cabinet, ...) have no joints, so an initial state does not hold their pose:
  LIBERO draws it from numpy's global generator at every reset. openpi seeds it once per task,
  so a trial's fixtures depend on the trials before it; here, as in `capvector evaluate`, trial i
  seeds it with 1_000_000 + i (`capvector.envs.base.EVAL_SEED_START`). robosuite 1.4's robot
  reset draws its (zero) initialisation noise from that generator before LIBERO places the
  fixtures, robosuite 1.5 from the env's own: the generator is seeded again after the robot's
  reset, so both place the fixtures from the same draws (the same poses, checked).
- A simulator exception fails the trial, as in openpi; a server error stops the run (openpi
  counts it as a failed trial).
- The cameras are drawn only on the steps whose observation is sent (the last wait step and the
  last step of each chunk), as `capvector evaluate` draws them: LIBERO's env draws both at every
  step, ~90% of a step's cost here, and a drawing changes no state. robosuite 1.4 samples a step's
  observables after its first physics substep (`Observable.update`: the sampling period equals
  the control period, so each step samples anew), so the images sent are those the env draws
  drawing at every step, to the bit (`--draw-every-step` draws them all, as openpi's client).

It prints a per-task table and `--json` writes rows in the shape of `capvector evaluate --json`
(each says its `stack`, robosuite 1.4's and MuJoCo's versions, and `renderer`),
each episode with its first action chunk and the state of every request besides success, steps,
reason and the final state (`final_proprio`); `--observations` writes the first request of every
trial as sent (npz).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import socket
import tempfile
import time
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
import robosuite
from libero.libero import benchmark
from libero.libero.envs import OffScreenRenderEnv
from openpi_client.websocket_client_policy import WebsocketClientPolicy

MAX_STEPS = {  # openpi's examples/libero/main.py: the longest training demo plus ~10%
    "libero_spatial": 220,
    "libero_object": 280,
    "libero_goal": 300,
    "libero_10": 520,
    "libero_90": 400,
}
CAMERAS = ("agentview", "robot0_eye_in_hand")  # openpi's observation/image, /wrist_image
NUM_WAIT_STEPS = 10
ERROR = "eval_client.py: error: "  # how a refusal starts (capvector evaluate shows that line)
WAIT_ACTION = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0]
FIXTURE_SEED_START = 1_000_000  # capvector.envs.base.EVAL_SEED_START


def quat2axisangle(quat_xyzw: np.ndarray) -> np.ndarray:
    """robosuite's `transform_utils.quat2axisangle`, as openpi's client computes the state."""
    w = min(max(float(quat_xyzw[3]), -1.0), 1.0)
    den = math.sqrt(1.0 - w * w)
    if math.isclose(den, 0.0):
        return np.zeros(3)
    return np.asarray(quat_xyzw[:3], dtype=np.float64) * 2.0 * math.acos(w) / den


def state_of(obs: dict[str, np.ndarray]) -> np.ndarray:
    """(8,) float32: eef position, axis-angle, two gripper joints (openpi's `observation/state`)."""
    return np.concatenate(
        [obs["robot0_eef_pos"], quat2axisangle(obs["robot0_eef_quat"]), obs["robot0_gripper_qpos"]]
    ).astype(np.float32)


def request_of(obs: dict[str, np.ndarray], instruction: str) -> dict[str, Any]:
    """openpi's LIBERO request: both cameras rotated 180° (LIBERO's training data is stored so)."""
    return {
        "observation/image": np.ascontiguousarray(obs["agentview_image"][::-1, ::-1]),
        "observation/wrist_image": np.ascontiguousarray(
            obs["robot0_eye_in_hand_image"][::-1, ::-1]
        ),
        "observation/state": state_of(obs),
        "prompt": instruction,
    }


# How capvector.eval.provenance names the stack, beside the port's "port (robosuite 1.5.2, ...)".
STACK = f"upstream LIBERO (robosuite {robosuite.__version__}, MuJoCo {mujoco.__version__})"
RENDERER = "official"  # robosuite's MuJoCo renderer, LIBERO's own images (capvector's name)


class SentCameras:
    """Draws the cameras only while ``drawing`` (module docstring): each image observable's
    sensor is wrapped to return its last image otherwise. The wrappers go on after every reset
    (a hard reset builds new sensors)."""

    def __init__(self, every_step: bool) -> None:
        self.every_step = every_step
        self.drawing = True

    def install(self, env: OffScreenRenderEnv) -> None:
        if self.every_step:
            return
        for name, observable in env.env._observables.items():
            sensor, last = observable._sensor, {}
            if observable.modality != "image" or hasattr(sensor, "sent_cameras"):
                continue  # a soft reset keeps the wrapped sensors

            def lazy(obs_cache: dict, sensor: Any = sensor, name: str = name, last: dict = last):
                if self.drawing or name not in last:
                    last[name] = sensor(obs_cache)
                return last[name]

            lazy.__modality__ = sensor.__modality__  # robosuite's @sensor marks it so
            lazy.sent_cameras = True
            observable._sensor = lazy

    def step(self, env: OffScreenRenderEnv, action: list[float], sent: bool) -> tuple:
        """One env step, drawing the cameras if its observation is ``sent`` to the policy."""
        self.drawing = sent or self.every_step
        return env.step(action)


class TrialFixtures:
    """Seeds numpy's global generator for a trial's reset, and again after the robot's reset, so
    LIBERO places the fixtures from the draws robosuite 1.5 gives it (module docstring)."""

    def __init__(self) -> None:
        self.seed = FIXTURE_SEED_START
        self.patched: set[type] = set()

    def reset(self, env: OffScreenRenderEnv, trial: int) -> None:
        robot_class = type(env.env.robots[0])  # the robots are rebuilt at every hard reset
        if robot_class not in self.patched:
            self.patched.add(robot_class)
            robot_reset = robot_class.reset

            def reset(robot: Any, *args: Any, **kwargs: Any) -> Any:
                out = robot_reset(robot, *args, **kwargs)
                np.random.seed(self.seed)
                return out

            robot_class.reset = reset
        self.seed = FIXTURE_SEED_START + trial
        np.random.seed(self.seed)
        env.seed(self.seed)
        env.reset()


def run_trial(
    env: OffScreenRenderEnv,
    fixtures: TrialFixtures,
    cameras: SentCameras,
    client: WebsocketClientPolicy,
    init_state: np.ndarray,
    trial: int,
    instruction: str,
    max_steps: int,
    replan_steps: int,
) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """One trial: its outcome (an episode of `capvector evaluate --json`, plus the first chunk,
    the state sent with every request and the final state) and its first request's arrays."""
    fixtures.reset(env, trial)
    cameras.install(env)
    obs = env.set_init_state(init_state)
    for wait in range(NUM_WAIT_STEPS):
        obs, _, _, _ = cameras.step(env, WAIT_ACTION, sent=wait == NUM_WAIT_STEPS - 1)
    first_request = request_of(obs, instruction)
    first_chunk: np.ndarray | None = None
    states: list[list[float]] = []
    steps, success, reason = 0, False, None
    while reason is None and not success:
        request = first_request if first_chunk is None else request_of(obs, instruction)
        chunk = np.asarray(client.infer(request)["actions"], dtype=np.float64)
        states.append(request["observation/state"].tolist())
        if first_chunk is None:
            first_chunk = chunk
        for i, action in enumerate(chunk[:replan_steps]):
            command = action.copy()
            command[-1] = 1.0 if command[-1] > 0 else -1.0  # binarised: module docstring
            try:
                obs, _, done, _ = cameras.step(env, command.tolist(), sent=i == replan_steps - 1)
            except Exception as e:  # as openpi: the trial fails, the evaluation goes on
                reason = f"{type(e).__name__} at step {steps}: {e}"
                break
            steps += 1
            if done:
                success = True
                break
            if steps >= max_steps:
                reason = f"step limit ({max_steps}) reached"
                break
    assert first_chunk is not None
    episode = {
        "success": success,
        "steps": steps,
        "reason": reason,
        "first_chunk": first_chunk.tolist(),
        "states": states,
        "final_proprio": state_of(obs).tolist(),  # as capvector evaluate --json names it
    }
    return episode, first_request


def wilson_interval(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95% Wilson score interval, as `capvector evaluate` reports it."""
    if n == 0:
        return 0.0, 1.0
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return max(0.0, centre - half), min(1.0, centre + half)


def row_of(suite: str, task_id: int, instruction: str, episodes: list[dict[str, Any]]) -> dict:
    """A row of `capvector evaluate --json` (`SuccessRow.to_dict` and `per_episode`)."""
    n, successes = len(episodes), sum(e["success"] for e in episodes)
    return {
        "task": f"{suite}/{task_id}",
        "robot": "Panda",
        "variant": None,
        "episodes": n,
        "successes": successes,
        "success_rate": successes / n,
        "ci95": list(wilson_interval(successes, n)),
        "mean_steps": sum(e["steps"] for e in episodes) / n,
        "failures": sorted({e["reason"] for e in episodes if e["reason"]}),
        "instruction": instruction,
        "stack": STACK,
        "renderer": RENDERER,
        "outcomes": [[e["trial"], e["success"]] for e in episodes],
        "per_episode": episodes,
    }


def write_atomically(path: Path, data: bytes) -> None:
    """Temp file in the same folder, then rename: a reader never sees half a file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    with os.fdopen(fd, "wb") as fh:
        fh.write(data)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)  # as a plain open() would have made it, not mkstemp's 0600
    os.replace(tmp, path)


def check_cameras(meta: dict[str, Any]) -> None:
    """The policy's cameras are LIBERO's, in the order openpi's keys send them (agentview as
    `observation/image`, the wrist as `observation/wrist_image`)."""
    cameras = list(meta["cameras"])
    if cameras != list(CAMERAS[: len(cameras)]):
        raise SystemExit(
            f"{ERROR}the served policy sees cameras {cameras}; this client sends {list(CAMERAS)} in "
            "that order: serve a policy trained on LIBERO's cameras"
        )


def check_fovy(env: OffScreenRenderEnv, meta: dict[str, Any]) -> None:
    """The policy trained at the scene's fields of view where its metadata names them, as
    `capvector evaluate --suite` checks (LIBERO's cameras are fixed)."""
    model = env.env.sim.model
    for camera, degrees in (meta.get("camera_fovy") or {}).items():
        scene = float(model.cam_fovy[model.camera_name2id(camera)])
        if abs(scene - degrees) > 1e-3:
            env.close()  # before the message: robosuite's renderer dies noisily at exit
            raise SystemExit(
                f"{ERROR}the policy was trained with camera {camera} at a vertical field of view of "
                f"{degrees}°, LIBERO's scene has {scene}°: LIBERO's cameras are fixed, so "
                "evaluate a policy trained on LIBERO's views"
            )


def wait_for_server(host: str, port: int, timeout: float) -> None:
    """Return once ``host:port`` accepts a connection; exit with a message after ``timeout`` s.
    openpi's client waits for the server forever (a typo'd port or a server that crashed while
    loading would hang the evaluation), so the wait is bounded here before it connects."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            socket.create_connection((host, port), timeout=5).close()
            return
        except OSError as err:
            if time.monotonic() >= deadline:
                raise SystemExit(
                    f"{ERROR}no policy server answers at {host}:{port} after {timeout:.0f} s ({err}): "
                    "start `capvector serve --ckpt EXPORT --port PORT` first, or raise "
                    "--connect-timeout while a large model loads"
                ) from None
            time.sleep(1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=8000)
    parser.add_argument("--suite", default="libero_spatial", choices=sorted(MAX_STEPS))
    parser.add_argument("--tasks", type=int, nargs="*", help="task ids (default: all)")
    parser.add_argument("--trials", type=int, default=50, help="trials per task, 1..50")
    parser.add_argument("--max-steps", type=int, help="step limit (default: the suite's)")
    parser.add_argument("--image-size", type=int, help="render size (default: the policy's)")
    parser.add_argument("--replan-steps", type=int, help="actions per request (default: chunk)")
    parser.add_argument(
        "--draw-every-step", action="store_true",
        help="draw the cameras at every step, not only where the policy is asked (same images)",
    )  # fmt: skip
    parser.add_argument("--json", type=Path, help="write the rows, every episode's outcome")
    parser.add_argument("--observations", type=Path, help="write first requests' arrays (npz)")
    parser.add_argument(
        "--connect-timeout", type=float, default=600.0,
        help="seconds to wait for the server to accept connections (default 600)",
    )  # fmt: skip
    args = parser.parse_args()

    bench = benchmark.get_benchmark_dict()[args.suite]()
    tasks = range(bench.n_tasks) if args.tasks is None else args.tasks
    for task_id in tasks:
        if not 0 <= task_id < bench.n_tasks:
            parser.error(f"--tasks {task_id}: {args.suite} has tasks 0..{bench.n_tasks - 1}")
    if not 1 <= args.trials <= 50:
        parser.error(f"--trials {args.trials}: LIBERO has 50 initial states per task")
    wait_for_server(args.host, args.port, args.connect_timeout)
    client = WebsocketClientPolicy(args.host, args.port)
    meta = client.get_server_metadata()
    horizon = int(meta["action_horizon"])
    replan = args.replan_steps or horizon
    if not 1 <= replan <= horizon:
        parser.error(f"--replan-steps {replan}: the served chunk has {horizon} actions")
    check_cameras(meta)
    size = args.image_size or int(meta["image_size"])
    max_steps = args.max_steps or MAX_STEPS[args.suite]
    print(
        f"{args.suite}: {meta['preset']} served at {args.host}:{args.port}, {size} px, "
        f"{replan} of {horizon} actions per request, at most {max_steps} steps",
        flush=True,
    )

    rows, arrays, fixtures = [], {}, TrialFixtures()
    cameras = SentCameras(args.draw_every_step)
    for task_id in tasks:
        task = bench.get_task(task_id)
        env = OffScreenRenderEnv(
            bddl_file_name=bench.get_task_bddl_file_path(task_id),
            camera_heights=size,
            camera_widths=size,
        )
        check_fovy(env, meta)
        init_states = bench.get_task_init_states(task_id)
        episodes = []
        for trial in range(args.trials):
            episode, request = run_trial(
                env, fixtures, cameras, client, init_states[trial], trial, task.language,
                max_steps, replan,
            )  # fmt: skip
            episodes.append({"suite": args.suite, "task": task_id, "trial": trial, **episode})
            key = f"{args.suite}/{task_id}/{trial}"
            arrays.update(
                {
                    f"{key}/{name.split('/')[-1]}": v
                    for name, v in request.items()
                    if name != "prompt"
                }
            )
            print(
                f"{key}: {'success' if episode['success'] else 'failure'} after "
                f"{episode['steps']} steps{'; ' + episode['reason'] if episode['reason'] else ''}",
                flush=True,
            )
        env.close()
        rows.append(row_of(args.suite, task_id, task.language, episodes))

    print(f"\n{'task':<18} {'success':>9} {'mean steps':>11}  instruction")
    for row in rows:
        rate = f"{row['successes']}/{row['episodes']}"
        print(f"{row['task']:<18} {rate:>9} {row['mean_steps']:>11.1f}  {row['instruction']}")
    total, successes = sum(r["episodes"] for r in rows), sum(r["successes"] for r in rows)
    print(f"{args.suite + ' (all)':<18} {f'{successes}/{total}':>9}")
    if args.json:
        write_atomically(args.json, (json.dumps(rows, indent=1) + "\n").encode())
    if args.observations:
        with tempfile.TemporaryFile() as fh:
            np.savez_compressed(fh, **arrays)
            fh.seek(0)
            write_atomically(args.observations, fh.read())


if __name__ == "__main__":
    main()
