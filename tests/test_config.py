"""Every stage x task composes and instantiates; bad overrides and inconsistent values fail clearly."""
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.errors import ConfigCompositionException
from hydra.utils import instantiate
from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException

from tests.stage_runner import run as run_stage
from topocut.config import STAGES, ConfigError, register_configs, validate

CONF = str(Path(__file__).resolve().parents[1] / "conf")
TASKS = ("slice", "stick", "dice", "pyramid")
register_configs()


def _compose(*overrides):
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides))


@pytest.mark.parametrize("task", TASKS)
@pytest.mark.parametrize("stage", STAGES)
def test_every_stage_and_task_composes_validates_and_instantiates(stage, task):
    cfg = _compose(f"stage={stage}", f"task={task}", "logger=none")
    assert cfg.stage.name == stage and cfg.task.name == task
    validate(cfg)
    fn = instantiate(cfg.stage.run, _convert_="object")
    assert callable(fn)
    for key, value in fn.keywords.items():  # sub-configs arrive as their dataclasses
        node = cfg.stage.run[key]
        if OmegaConf.is_config(node) and OmegaConf.get_type(node) not in (dict, list):
            assert type(value) is OmegaConf.get_type(node), key


@pytest.mark.parametrize("scale", ["smoke", "paper"])
def test_scales_compose(scale):
    cfg = _compose(f"scale={scale}")
    validate(cfg)
    assert cfg.sim.n_grid == {"smoke": 48, "paper": 128}[scale]  # the scale sets sizes across groups


def test_every_object_and_model_composes():
    for obj in ("cake", "cube", "ditto", "ham", "potato", "donut", "burger", "sushi", "steak", "tomato"):
        validate(_compose(f"object={obj}"))
    for model in ("graph_transformer", "pointnet"):
        assert _compose(f"model={model}").model.model == model


def test_typo_in_group_choice_lists_valid_choices():
    with pytest.raises(ConfigCompositionException, match="(?s)Could not find 'stage/mpi'.*mppi"):
        _compose("stage=mpi")
    with pytest.raises(ConfigCompositionException, match="(?s)object/carrot.*cake"):
        _compose("object=carrot")


def test_typo_in_key_fails_naming_it():
    with pytest.raises(ConfigCompositionException) as e:
        _compose("sim.n_grd=32")
    assert isinstance(e.value.__cause__, OmegaConfBaseException) and "sim.n_grd" in str(e.value.__cause__)
    with pytest.raises(ConfigCompositionException) as e:
        _compose("sim.n_grid=abc")
    assert "n_grid" in str(e.value.__cause__)


def test_cfl_violation_names_the_key():
    cfg = _compose("sim.dt=0.05")
    with pytest.raises(ConfigError, match=r"sim\.dt"):
        validate(cfg)


def test_misspelt_stage_argument_names_the_key():
    cfg = _compose("stage=mppi", "+stage.run.episods=3")
    with pytest.raises(ConfigError, match=r"stage\.run\.episods.*valid"):
        validate(cfg)


def test_bad_device_value():
    cfg = _compose("device=tpu")
    with pytest.raises(ConfigError, match="device"):
        validate(cfg)


def test_cuda_request_without_a_gpu_is_an_error_not_a_silent_cpu_run():
    import torch

    from topocut.utils.runtime import DeviceUnavailable, resolve_device

    if torch.cuda.is_available():
        pytest.skip("this machine has a GPU")
    with pytest.raises(DeviceUnavailable, match="device=cuda"):
        resolve_device("cuda")
    assert resolve_device("auto") == "cpu"
    with pytest.raises(ValueError, match="auto, cpu, cuda"):
        resolve_device("tpu")


def test_stick_with_one_cut_is_refused_naming_the_key():
    cfg = _compose("task=stick", "task.max_cuts=1")
    with pytest.raises(ConfigError, match=r"task\.max_cuts.*at least 2"):
        validate(cfg)


@pytest.mark.parametrize("override, key", [
    ("eval.seen=[cake,bagel]", r"eval\.seen: unknown object 'bagel'"),
    ("eval.unseen=[donut,Steak]", r"eval\.unseen: unknown object 'Steak'"),
    ("trainer.held_out_objects=[donuts]", r"trainer\.held_out_objects: unknown object 'donuts'"),
    ("data.episodes=0", r"data\.episodes: 0 .*>= 1"),
    ("data.points_per_step=-5", r"data\.points_per_step: -5 .*>= 1"),
    ("trainer.max_epochs=0", r"trainer\.max_epochs: 0 "),
    ("trainer.batch_size=0", r"trainer\.batch_size: 0 .*>= 1"),
    ("seed=-1", r"seed: -1 .*2\*\*31 - 1"),
    ("seed=2147483647", r"seed: 2147483647 "),
    ("trainer.max_steps=0", r"trainer\.max_steps: 0 "),
    ("trainer.profiler=fast", r"trainer\.profiler: 'fast' .*valid: none, simple, advanced, pytorch"),
    ("model.emd_rounds=-1", r"model\.emd_rounds=-1 must be >= 0"),
    ("model.emd_tol=0", r"model\.emd_tol=0\.0 must be > 0"),
    ("policy.train.sample=gpu", r"policy\.train\.sample: 'gpu' is not valid; valid: loader, batch"),
])
def test_out_of_range_values_fail_up_front_naming_the_key(override, key):
    """Caught at composition, before a simulator or a dataset is touched (they failed deep in a stage before)."""
    cfg = _compose("stage=eval", override)
    with pytest.raises(ConfigError, match=key):
        validate(cfg)


def test_videos_without_an_encoder_are_refused_up_front_naming_the_key(monkeypatch):
    """The lent GPU machines have no ffmpeg: an evaluation that films is refused before it starts (it failed after its
    last episode before), a run that evaluates nothing or films nothing is not."""
    from topocut.eval import videos

    assert videos.encoder_problem() is None  # this machine films (pyproject's matplotlib, imageio, imageio-ffmpeg)
    monkeypatch.setattr(videos, "encoder_problem", lambda: "ModuleNotFoundError: No module named 'imageio_ffmpeg'")
    for stage in ("eval", "all"):
        with pytest.raises(ConfigError, match=r"eval\.videos: 1 films MP4s, .*imageio_ffmpeg.*set eval\.videos=0"):
            validate(_compose(f"stage={stage}", "eval.videos=1"))
    validate(_compose("stage=eval", "eval.videos=0"))
    validate(_compose("stage=all", "eval.videos=1", "stage.run.sequence=[simulate,mppi]"))
    validate(_compose("stage=mppi", "eval.videos=1"))


def test_boundary_values_pass():
    validate(_compose("stage=eval", "data.episodes=1", "trainer.batch_size=1", "seed=2147483646",
                      "trainer.max_epochs=-1", "trainer.max_steps=10", "eval.unseen=[tomato]"))


def test_help_lists_every_group_choice_and_examples():
    import sys

    proc = run_stage([sys.executable, "-m", "topocut.run", "--help"], timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    for line in ("stage: all, bc, eval, merge, mppi, pretrain, simulate, teleop",
                 "object: burger, cake, cube, ditto, donut, ham, potato, steak, sushi, tomato",
                 "python -m topocut.run stage=mppi task=dice object=potato seed=3"):
        assert line in proc.stdout, proc.stdout


def test_open_dicts_take_new_keys_from_the_command_line():
    """`eval.task_overrides={slice:{...}}` as documented: under scale=paper (which sets no such key) OmegaConf's
    struct flag refused the new key; the entry point gives open-dict overrides Hydra's `++`."""
    import sys

    from hydra.errors import ConfigCompositionException

    from topocut.run import open_dict_overrides

    argv = ["scale=paper", "eval.task_overrides={slice:{thickness:0.05}}", "eval.checkpoints.pddp=v002",
            "+eval.policy_kwargs.M={a:1}", "eval.tasks=[slice]", "eval.checkpoints_x=1"]
    assert open_dict_overrides(argv) == ["scale=paper", "++eval.task_overrides={slice:{thickness:0.05}}",
                                         "++eval.checkpoints.pddp=v002", "+eval.policy_kwargs.M={a:1}",
                                         "eval.tasks=[slice]", "eval.checkpoints_x=1"]
    with pytest.raises(ConfigCompositionException, match="task_overrides"):  # what the rewrite is for
        _compose("stage=eval", "scale=paper", "eval.task_overrides={slice:{thickness:0.05}}")
    proc = run_stage([sys.executable, "-m", "topocut.run", "stage=eval", "scale=paper",
                      "eval.task_overrides={slice:{thickness:0.05}}", "--cfg", "job", "-p", "eval.task_overrides"],
                     timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "thickness: 0.05" in proc.stdout, proc.stdout


def test_seeding_matches_lightning_without_importing_it():
    """seed_everything_all draws what Lightning's seed_everything(workers=True) draws (python, numpy, torch) and
    sets its worker variables, in a process that never imports Lightning (its import costs a stage=mppi process
    30-40 s on the GPU machine)."""
    import subprocess
    import sys

    code = ("import sys, random, numpy as np, torch, os\n"
            "from topocut.utils.runtime import seed_everything_all\n"
            "seed_everything_all(11)\n"
            "print(random.random(), np.random.rand(), float(torch.rand(1)), os.environ['PL_GLOBAL_SEED'],"
            " os.environ['PL_SEED_WORKERS'], 'lightning' in sys.modules)\n"
            "from lightning.pytorch import seed_everything\n"
            "seed_everything(11, workers=True, verbose=False)\n"
            "print(random.random(), np.random.rand(), float(torch.rand(1)), os.environ['PL_GLOBAL_SEED'],"
            " os.environ['PL_SEED_WORKERS'])\n")
    ours, theirs = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                                  check=True).stdout.split("\n")[:2]
    assert ours.endswith(" False")  # Lightning not imported
    assert ours.rsplit(" ", 1)[0] == theirs


def test_host_threads_follow_omp_num_threads(monkeypatch):
    """host_threads: OMP_NUM_THREADS when set (joblib's workers get cpu_count // n_jobs), else every core."""
    import os

    from topocut.utils.runtime import host_threads

    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    assert host_threads() == 3
    for value in ("", "0", "x"):
        monkeypatch.setenv("OMP_NUM_THREADS", value)
        assert host_threads() == (os.cpu_count() or 1)
    monkeypatch.delenv("OMP_NUM_THREADS")
    assert host_threads() == (os.cpu_count() or 1)
