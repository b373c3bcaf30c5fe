"""The one parser of the ``imac-model`` command line. It imports nothing heavy; each command's
body is its module's ``run(args)``."""

from __future__ import annotations

import argparse

from imac_model.modes import MODES

__all__ = ["build_parser", "COMMANDS", "command_of"]

COMMANDS = {  # command -> the module whose run(args) carries it out
    "train": "imac_model.cli.train",
    "sample": "imac_model.cli.sample",
    "evaluate": "imac_model.cli.evaluate",
    "experiment": "imac_model.cli.experiment",
    "ranking": "imac_model.cli.ranking",
    "plan": "imac_model.cli.plan",
}
EXPERIMENT_STAGES = ("record", "build", "decode", "train", "evaluate", "report")
# the ranking benchmark's stages (imac_model.experiments.ranking.plan.STAGES, named here without importing it;
# tests/test_ranking.py keeps the two equal)
RANKING_STAGES = ("simulate", "build", "decode", "pack", "train", "judges", "evaluate", "report")


def _train(p: argparse.ArgumentParser) -> None:
    p.add_argument("--dataset", help="LeRobot repo id (overrides data.dataset)")
    p.add_argument("--root", help="dataset directory (overrides data.root)")
    p.add_argument("--config", help="run config (YAML/JSON); defaults for anything it leaves out")
    p.add_argument("--mode", choices=list(MODES), help="conditioning mode (overrides conditioning.mode)")
    p.add_argument("--output-dir", help="overrides train.output_dir")
    p.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                   help="override any field, e.g. --set train.max_steps=100 --set data.held_out_episodes=[8,9]")
    p.add_argument("--resume", action=argparse.BooleanOptionalAction, default=None,
                   help="continue from the output directory's latest checkpoint (default: when it has one)")
    p.add_argument("--no-progress", action="store_true")


def _sample(p: argparse.ArgumentParser) -> None:
    p.add_argument("--checkpoint", required=True, help="checkpoint directory, or a run directory (latest checkpoint)")
    p.add_argument("--episode", type=int, nargs="+", required=True, help="episode(s); several only with --evaluate")
    p.add_argument("--chunk", type=int, default=0, help="which chunk of the episode (default: the first)")
    p.add_argument("--chunks", type=int, default=1,
                   help="roll out this many chunks autoregressively from --chunk, rebuilding the controls from the "
                        "generated depth at every chunk boundary (default 1)")
    p.add_argument("--recorded-states", action="store_true",
                   help="with --chunks: the robot state at each boundary is the recorded one, not the last command")
    p.add_argument("--evaluate", action="store_true",
                   help="no video: sample every chunk of the episodes and print the mean errors")
    p.add_argument("--dataset", help="LeRobot repo id (default: the one the model was trained on)")
    p.add_argument("--root", help="dataset directory (default: the training run's)")
    p.add_argument("--out", help="mp4 path (default: <checkpoint>/samples/episode_<N>_chunk_<C>.mp4)")
    p.add_argument("--png", help="also write a still of the first, middle and last future frame here")
    p.add_argument("--steps", type=int, help="Euler steps (default: the model's flow.sample_steps)")
    p.add_argument("--guidance", type=float,
                   help="classifier-free guidance by the controls (default: the model's conditioning.guidance, 1; "
                        "needs a model trained with conditioning.dropout)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--weights", choices=("ema", "raw"), default="ema")
    p.add_argument("--scale", type=int, default=2, help="pixel upscale of the written images")


def _model_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--checkpoint", required=True, help="world-model checkpoint directory or run directory")
    p.add_argument("--mode", help="the conditioning mode you mean to evaluate; a checkpoint trained with another "
                                  f"is refused ({', '.join(MODES)})")
    p.add_argument("--dataset", help="LeRobot repo id of the source dataset (default: the model's)")
    p.add_argument("--root", help="source dataset directory (default: the training run's)")
    p.add_argument("--episodes", type=int, nargs="+",
                   help="start episodes (default: the run's held-out episodes, else all)")
    p.add_argument("--steps", type=int, help="sampler (Euler) steps (default: the model's flow.sample_steps)")
    p.add_argument("--guidance", type=float,
                   help="classifier-free guidance by the controls (default: the model's conditioning.guidance, 1; "
                        "needs a model trained with conditioning.dropout)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--weights", choices=("ema", "raw"), default="ema")
    p.add_argument("--device", default="cpu")
    p.add_argument("--no-progress", action="store_true")


def _evaluate(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="evaluate_command", required=True, metavar="EVALUATE_COMMAND")

    c = sub.add_parser("closed-loop", help="run a policy in the world model; write a LeRobot dataset of its episodes")
    _model_args(c)
    c.add_argument("--policy", required=True,
                   help="recorded (replay each start episode's actions), hold, lerobot:DIR (a LeRobot policy "
                        "checkpoint directory) or python:MODULE:NAME (a callable observation -> (K, D) actions); "
                        "noisy:STD:SPEC adds Gaussian noise of STD (action units) to every action of SPEC")
    c.add_argument("--camera-map", nargs="+", metavar="POLICY_KEY=VIEW",
                   help="lerobot policies: which world-model view feeds each of the policy's camera keys "
                        "(default: observation.images.X reads view X)")
    c.add_argument("--output", required=True, help="directory of the LeRobot dataset of generated episodes")
    c.add_argument("--repo-id", help="its repo id (default local/<output name>)")
    c.add_argument("--overwrite", action="store_true")
    c.add_argument("--horizon-chunks", type=int,
                   help="world-model chunks per episode (default: enough to cover each recorded episode)")
    c.add_argument("--success-classifier", help="a saved SuccessClassifier directory: judges every episode")
    c.add_argument("--judge", help="judges every episode: classifier:DIR or python:MODULE:NAME (a SuccessJudge, or "
                                   "a function EpisodeFrames -> bool)")
    c.add_argument("--judge-frames", type=int, default=4, help="last frames per view the judge sees")
    c.add_argument("--json", help="result JSON (default <output>/closed_loop.json)")

    m = sub.add_parser("simulator", help="run a policy in MuJoCo (the simulated ALOHA rig) under the closed loop's "
                                         "observation contract; write HDF5 episodes with their success")
    m.add_argument("--policy", required=True,
                   help="hold, lerobot:DIR, python:MODULE:NAME or noisy:STD:SPEC (as closed-loop)")
    m.add_argument("--task", default="lift", help="simulated task (default lift)")
    m.add_argument("--seeds", nargs="+", required=True, metavar="SEED",
                   help="episode start seeds (gym-aloha's reset(seed)), one episode each: integers or inclusive "
                        "ranges A..B (0..24 100 is 26 episodes)")
    m.add_argument("--chunks", type=int, default=4, help="policy chunks per episode (default 4)")
    m.add_argument("--chunk", type=int, default=8, help="actions per chunk: the world model's H (default 8)")
    m.add_argument("--view-size", type=int, nargs=2, default=(48, 64), metavar=("H", "W"),
                   help="what the policy sees: the world model's view size (default 48 64)")
    m.add_argument("--render-size", type=int, nargs=2, default=(96, 128), metavar=("H", "W"),
                   help="what is rendered and recorded (default 96 128)")
    m.add_argument("--views", nargs="+", default=("cam_high", "cam_left_wrist", "cam_right_wrist"),
                   help="the cameras the policy sees, in order (default the three ALOHA cameras; every camera "
                        "of the rig, cam_workspace included, is recorded)")
    m.add_argument("--settle", type=float, default=0.0, metavar="SECONDS",
                   help="let the physics run this long before the first frame (gym-aloha's box starts 3 cm above "
                        "the table and falls; default 0: its start as is)")
    m.add_argument("--output", help="directory for episode_<i>.hdf5 and calibration.json (build it with imac build "
                                    "--recipe recipes/aloha_sim_lift.yaml --source DIR)")
    m.add_argument("--json", help="outcomes JSON (default <output>/outcomes.json, or none without --output)")
    m.add_argument("--no-progress", action="store_true")

    v = sub.add_parser("video-metrics", help="rollouts of the recorded actions against the recording")
    _model_args(v)
    v.add_argument("--chunks", type=int, default=1, help="chunks per rollout (default 1)")
    v.add_argument("--metrics", nargs="+", default=["mse", "psnr", "ssim"],
                   help="of mse psnr ssim fid fvd (FID/FVD need local weights, see docs/evaluation.md)")
    v.add_argument("--fid-weights", help="FID Inception weights file (default under $XDG_CACHE_HOME/imac/weights)")
    v.add_argument("--fvd-weights", help="FVD I3D weights file (default under $XDG_CACHE_HOME/imac/weights)")
    v.add_argument("--batch-size", type=int, default=8)
    v.add_argument("--json", required=True, help="result JSON")

    lab = sub.add_parser("label", help="import success labels (CSV episode_index,success) into generated episodes")
    lab.add_argument("--dataset", required=True, help="directory of a dataset written by closed-loop")
    lab.add_argument("--labels", required=True, help="CSV with columns episode_index, success")
    lab.add_argument("--repo-id")
    lab.add_argument("--json", help="also write the labels and success rate here")

    r = sub.add_parser("correlate", help="world-model vs real success: correlations, MMRV, bootstrap, scatter plot")
    r.add_argument("--outcomes", required=True,
                   help="CSV (policy,group,source,success; source world_model or real) or JSON "
                        "{world_model: {policy: [..]}, real: {...}}")
    r.add_argument("--json", required=True, help="result JSON")
    r.add_argument("--png", help="scatter plot (PNG)")
    r.add_argument("--title")
    r.add_argument("--replicates", type=int, default=2000)
    r.add_argument("--confidence", type=float, default=0.95)
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--paired", action="store_true", help="resample world-model and real episodes together")
    r.add_argument("--normalize", default="none", choices=("none", "max", "minmax"),
                   help="rates normalised per side before the statistics (default none)")
    r.add_argument("--interval", default="bc", choices=("bc", "percentile", "basic"),
                   help="bootstrap interval (default bc, bias-corrected)")


def _experiment(p: argparse.ArgumentParser) -> None:
    p.add_argument("--work", default="runs/experiment", help="cache of every stage (resumable)")
    p.add_argument("--docs", default="docs/experiment", help="where the report goes")
    p.add_argument("--episodes", type=int, default=44)
    p.add_argument("--held-out", type=int, default=8, help="the last N episodes are held out")
    p.add_argument("--cpu-minutes", type=float, default=15.0, help="training budget per setting (process CPU minutes)")
    p.add_argument("--jobs", type=int, default=5, help="settings trained at once")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--steps", type=int, help="Euler steps at evaluation (default: the model's, 20)")
    p.add_argument("--warmup-epochs", type=float, default=5.0,
                   help="the rollout setting's epochs of ordinary steps before rollout (default 5)")
    p.add_argument("--stages", default=",".join(EXPERIMENT_STAGES),
                   help=f"comma-separated subset of {','.join(EXPERIMENT_STAGES)}")
    p.add_argument("--internal", choices=("decode", "evaluate"), help=argparse.SUPPRESS)
    p.add_argument("--setting", help=argparse.SUPPRESS)


def _ranking(p: argparse.ArgumentParser) -> None:
    p.add_argument("--work", default="runs/ranking", help="cache of every stage (resumable)")
    p.add_argument("--docs", help="where the report goes (default: where the work directory's run put it, else docs/ranking; "
                        "with --from-models, <work>/report)")
    p.add_argument("--policies", nargs="+", metavar="SPEC",
                   help="python:MODULE:NAME or lerobot:DIR policies to rank (default: the preset's; with "
                        "--from-models, the report's)")
    p.add_argument("--from-models", nargs="?", const="docs/ranking/models", metavar="DIR",
                   help="rank with the world models shipped in DIR (default docs/ranking/models), with no training: "
                        "the report beside DIR's plan, on --policies, its rows put beside the report's "
                        "(docs/ranking.md, 'The shipped world models')")
    p.add_argument("--starts", type=int, metavar="K",
                   help="with --from-models: only the report's first K starts (a quick check of its verdicts)")
    p.add_argument("--modes", nargs="+", metavar="MODE",
                   help="the world models trained and compared, MODE or MODE@seedK for another training seed (default: "
                        "the preset's; e.g. motion+contact none for a first look at new training data)")
    p.add_argument("--cpu-minutes", type=float, help="training budget per compared mode (default 120)")
    p.add_argument("--gpu-minutes", type=float, metavar="MINUTES",
                   help="train the compared modes on one GPU instead, MINUTES of wall time each, from the tensor pack "
                        "(any preset; --preset gpu sets 8): the pack stage, scripts/gpu_train.py, --import-gpu "
                        "(docs/ranking.md, 'The GPU preset')")
    p.add_argument("--set", action="append", metavar="FIELD=VALUE",
                   help="a run-config field for every trained mode, kept in the plan (repeatable; e.g. "
                        "train.max_steps=10000 with train.cpu_threads=2 and a --cpu-minutes it stays under: a budget "
                        "in steps on both cores)")
    p.add_argument("--steps", type=int, help="Euler steps at evaluation (default 10)")
    p.add_argument("--jobs", type=int, help="processes at a time (default 2)")
    p.add_argument("--training-offsets", metavar="NAME",
                   help="how far off the cube the world model's training rollouts grasp: across (default), slope "
                        "(half of them where the success rate falls) or disc (work directories made before "
                        "2026-11-28); the plan checks it against policies.TRAINING_OFFSETS (docs/ranking.md, "
                        "'Training data that covers the policies')")
    p.add_argument("--training-policies", nargs="+", metavar="SPEC",
                   help="policies (python:, lerobot:, noisy: specs) whose own rollouts join the world model's training "
                        "data, in turn, at --training-policy-share of the rollouts; e.g. checkpoints of the ranked "
                        "policy's training run that are not ranked (docs/ranking.md, 'Training on the ranked family')")
    p.add_argument("--training-policy-share", type=float, metavar="SHARE",
                   help="share of the training rollouts the --training-policies run, spread evenly (default 0.25)")
    p.add_argument("--settle", type=float, metavar="SECONDS",
                   help="physics run before each episode's first frame, so the box gym-aloha starts 3 cm up rests "
                        "on the table (default 0.3; work directories made before 2026-11-29: 0)")
    p.add_argument("--views", nargs="+", metavar="CAMERA",
                   help="the cameras the policies, the judges and the world model see; the world model generates "
                        "them (default cam_workspace; work directories made before 2026-11-29: cam_workspace "
                        "cam_right_wrist; the workspace view is required: the judge reads it; docs/ranking.md, "
                        "'The views')")
    p.add_argument("--toy", action="store_true", help="the CI size: tiny backbone, 2 policies, 4 episodes, "
                                                       "2 chunks, 2 modes, 2 sampler steps")
    p.add_argument("--preset", choices=("cpu", "gpu", "checkpoints"), default="cpu",
                   help="cpu (default: every mode trained on the CPU budget), gpu (motion+contact and "
                        "action-vector trained 8 minutes each on one GPU from the tensor pack) or checkpoints (the "
                        "graded scripted policies and lerobot-train checkpoints, 100 starts, 3 training seeds: "
                        "imac_model/configs/ranking_checkpoints.yaml); docs/ranking.md")
    p.add_argument("--stages", help=f"comma-separated subset of {','.join(RANKING_STAGES)} (default: every stage "
                                    "the preset needs; pack, the GPU's training tensors, with --preset gpu only)")
    p.add_argument("--plan", help=argparse.SUPPRESS)
    p.add_argument("--import-gpu", metavar="DIR", help="put the run archives in DIR (<run>.tar from scripts/gpu_train.py, "
                                                      "or <run>.tar.xz from --export-runs) into the work directory as "
                                                      "trained runs (docs/ranking.md, 'The GPU preset')")
    p.add_argument("--export-runs", metavar="DIR", help="write trained runs as DIR/<run>.tar.xz (latest checkpoint as "
                                                       "it ships, whole log, early gates), to keep or carry to a later "
                                                       "loan or session (docs/ranking.md, 'Weights between loans')")
    p.add_argument("--runs", nargs="+", metavar="RUN", help="with --export-runs: these runs under <work>/runs "
                                                            "(default: the plan's modes')")
    p.add_argument("--status", action="store_true",
                   help="say where --work's run stands (stages done, training, gates, evaluation) and exit; it takes "
                        "no lock, so it answers while a run works there")
    p.add_argument("--rewrite-report", action="store_true",
                   help="write --docs's README.md again from its results.json alone (after a change of the report's "
                        "text; no work directory needed, no picture redrawn)")
    p.add_argument("--internal", choices=("train-rollouts", "decode", "pack", "judges", "evaluate", "replays", "gate"),
                   help=argparse.SUPPRESS)
    p.add_argument("internal_args", nargs="*", help=argparse.SUPPRESS)


def _plan(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", required=True, help="run config (YAML/JSON); it must set data.view_width and data.chunk")
    p.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE", help="override any field, as in train")
    p.add_argument("--gpus", type=int, nargs="+", default=[1, 8], help="GPU counts to plan for (default 1 8)")
    p.add_argument("--gpu-gb", type=float, default=80.0, help="memory of one GPU in GB of 1e9 bytes (default 80)")
    p.add_argument("--reserve-gb", type=float, default=4.0,
                   help="kept free for the CUDA context, NCCL buffers and fragmentation (default 4)")
    p.add_argument("--micro-batch", type=int, help="samples per GPU per step (default: train.batch_size / GPUs)")
    p.add_argument("--views", type=int, help="camera views (default: data.views, else 3)")
    p.add_argument("--action-dim", type=int, default=14, help="action dimension (action-vector mode; default 14)")
    p.add_argument("--json", help="also write the plan here as JSON")


def build_parser(prog: str = "imac-model") -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=prog, description="The iMaC world model: train, sample, evaluate, plan; "
                                                            "the experiments. docs/world-model.md has the details.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    _train(sub.add_parser("train", help="train the world model on an imac dataset"))
    _sample(sub.add_parser("sample", help="generate chunks of a dataset episode and show them beside the recording"))
    _evaluate(sub.add_parser("evaluate", help="closed-loop policy evaluation, video metrics, success labels, "
                                              "world-model vs real correlations"))
    _experiment(sub.add_parser("experiment", help="the small-scale comparison of docs/experiment (resumable)"))
    _ranking(sub.add_parser("ranking", help="does the world model rank policies as MuJoCo does? (docs/ranking.md, "
                                            "resumable)"))
    _plan(sub.add_parser("plan", help="memory and compute plan of a run config on the meta device (no GPU, no "
                                      "weights): parameters, bytes per GPU, activations, tokens, FLOPs, what fits"))
    return parser


def command_of(args: argparse.Namespace) -> str:
    return args.command
