"""Policy and training configuration: one frozen dataclass, presets `small` and `full`, TOML overrides.

The recipe is Diffusion Policy (Chi et al., RSS 2023), CNN variant: observation horizon To=2, prediction
horizon Tp=16, execution horizon Ta=8; DDPM with 100 training steps, squaredcos_cap_v2 betas, epsilon
prediction; DDIM at inference; a 1-D conditional UNet with FiLM; a from-scratch ResNet per camera with
GroupNorm (BatchNorm statistics do not survive EMA averaging) and a spatial-softmax head; AdamW 1e-4 with
cosine decay after a linear warm-up; EMA of the weights.

- `small` trains on a 2-core CPU in minutes and runs a chunk (obs encoding + 8 DDIM steps) in ~15-25 ms
  with onnxruntime: 96x96 random crops of the 128x128 images, one residual block per stage at widths
  16-32-64-128 (both cameras: 0.67 M parameters, plus 0.37 M for the instruction's FiLM), UNet down_dims
  (64, 128, 256) with temporal kernel 3 and a 64-D step embedding (4.3 M); 5.3 M in all. On a CPU the
  denoiser is bound by per-op overhead, so its kernel and widths were chosen for parameter count, not
  speed. The encoder's widths are what cost time: 32-64-128-256 (2.5 M) measured ~3x the encoder latency;
  set it in a TOML file when data warrants.
- `full` is the paper's size for a GPU: ResNet-18 widths and depth (64-128-256-512, two blocks per stage),
  down_dims (256, 512, 1024), 112x112 crops.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

from datagen.schema import ACTION_DIM, CAMERAS, IMAGE_SIZE, PROPRIO_DIM
from sim.config import ConfigError, as_dict, load_config, spec

PRESETS = ("small", "full")
TEXT_DIM = 384  # all-MiniLM-L6-v2
AUX_DIM = 6  # the aux head's grasp and release points
# metres -> units of the "tcp" auxiliary target: offsets across the reachable table come out about unit size
AUX_TCP_SCALE = 0.25
AXIS_DIM = 2  # with aux_grasp_axis: the grasp axis after them (policy/grasp_axis.py)


@dataclass(frozen=True)
class PolicyConfig:
    """Everything that defines a policy and how it is trained; recorded in every run and bundle."""

    preset: str = field(default="small", metadata=spec(choices=PRESETS))
    # horizons (steps at datagen.schema.CONTROL_HZ)
    obs_horizon: int = field(default=2, metadata=spec(1, 16, doc="To: observation steps fed to the policy"))
    pred_horizon: int = field(default=16, metadata=spec(4, 64, doc="Tp: predicted actions; multiple of 4"))
    action_horizon: int = field(default=8, metadata=spec(1, 64, doc="Ta: actions executed per chunk"))
    # observations
    cameras: tuple[str, ...] = field(default=CAMERAS, metadata=spec(choices=CAMERAS))
    image_size: tuple[int, int] = field(default=IMAGE_SIZE, metadata=spec(16, 1024, "px", doc="dataset H, W"))
    crop_size: tuple[int, int] = field(default=(96, 96), metadata=spec(8, 1024, "px",
                                       doc="random crop (train) / centre crop (inference) H, W"))
    proprio_dim: int = field(default=PROPRIO_DIM, metadata=spec(1, 256))
    action_dim: int = field(default=ACTION_DIM, metadata=spec(1, 256))
    # image encoder
    encoder_widths: tuple[int, ...] = field(default=(16, 32, 64, 128), metadata=spec(4, 1024))
    encoder_blocks: tuple[int, ...] = field(default=(1, 1, 1, 1), metadata=spec(1, 8))
    # Stride of each stage's first block; empty = the ResNet's 1, 2, 2, ... That leaves a 3x3 map of a
    # 96x96 crop for the spatial softmax: nine cells to say where a 4 cm object is; 1-2-2-1 keeps 6x6.
    encoder_strides: tuple[int, ...] = field(default=(), metadata=spec(1, 4))
    keypoints: int = field(default=32, metadata=spec(1, 512, doc="spatial-softmax keypoints per camera"))
    image_feature_dim: int = field(default=64, metadata=spec(1, 2048))
    # Early fusion (as RT-1's FiLM-EfficientNet): the instruction scales and shifts every residual block's
    # channels, so the spatial-softmax keypoints can follow *the named* object. Without it the keypoints are
    # instruction-blind and 300 demos did not teach the denoiser to pick the target among distractors.
    text_film: bool = True
    # The instruction as [sentence embedding, goal clause embedding] (policy.instruction): MiniLM's mean pooling
    # leaves "stack A on B" and "stack B on A" 0.997 alike; the goal clause ("on the B") says which is which.
    text_goal: bool = False
    stage_bins: int = field(default=0, metadata=spec(0, 8, doc=(
        "grasp cycles completed so far (policy/stage.py: the gripper held something and let it go), read "
        "with the proprio as a one-hot of this many classes (the last: that many or more), so a multi-grasp "
        "task (drawer_put: handle, object, handle) knows which grasp comes next; 0 = not read")))
    proprio_feature_dim: int = field(default=64, metadata=spec(1, 2048))
    text_feature_dim: int = field(default=64, metadata=spec(1, 2048))
    # denoiser
    down_dims: tuple[int, ...] = field(default=(64, 128, 256), metadata=spec(4, 4096))
    kernel_size: int = field(default=3, metadata=spec(1, 15, doc="temporal conv kernel (the paper: 5)"))
    step_embed_dim: int = field(default=64, metadata=spec(8, 1024))
    group_norm_groups: int = field(default=8, metadata=spec(1, 64, doc="UNet; the image encoder uses width/16"))
    # diffusion
    num_train_timesteps: int = field(default=100, metadata=spec(2, 1000))
    beta_schedule: str = field(default="squaredcos_cap_v2", metadata=spec(choices=("squaredcos_cap_v2", "linear")))
    objective: str = field(default="ddpm", metadata=spec(choices=("ddpm", "flow"), doc=(
        "ddpm: epsilon prediction, DDIM sampling; flow: flow matching (velocity of the straight noise-to-action "
        "path), Euler sampling, good in few steps")))
    inference_steps: int = field(default=8, metadata=spec(1, 1000, doc="DDIM or Euler steps"))
    noise_scale: float = field(default=1.0, metadata=spec(0.0, 1.0, doc=(
        "sampling temperature: the sampler starts from N(0, noise_scale^2 I); below 1 it keeps to the denser "
        "middle of the learned chunks (0: one deterministic chunk per observation); training is unaffected")))
    clip_sample: bool = True
    # data
    include_failures: bool = False
    subtask_language_prob: float = field(default=0.0, metadata=spec(0.0, 1.0,
                                         doc="share of samples conditioned on the running subtask's label"))
    aux_target_weight: float = field(default=0.0, metadata=spec(0.0, 100.0, doc=(
        "weight of an auxiliary loss: regress, from the current image features alone, where the episode "
        "grasps and releases (the actions' first gripper close and the next open); 0 = off")))
    aux_target_frame: str = field(default="base", metadata=spec(choices=("base", "tcp"), doc=(
        "frame of those targets: base (absolute, normalized like the actions) or tcp (relative to the "
        "gripper at the sample's newest step: what the wrist camera sees directly)")))
    aux_condition: bool = field(default=False, metadata=spec(doc=(
        "feed the aux head's grasp and release points to the denoiser as 6 more conditioning inputs, so the "
        "chunk is drawn towards where the images say the object is (needs aux_target_weight > 0); training "
        "feeds the true points plus aux_condition_noise, inference the head's prediction (exported in "
        "obs_encoder.onnx)")))
    aux_release_frame: str = field(default="tcp", metadata=spec(choices=("tcp", "base"), doc=(
        "frame in which the aux head reads the release point: tcp (with the grasp point, relative to the "
        "gripper) or base (where the bin is, which no arm pose changes: the denoiser still gets it relative to "
        "the gripper, turned there in the graph from the newest proprio); needs aux_target_frame tcp. Pretrained "
        "on approach views only, the head finds it 1.8 cm off while carrying (14.5 cm relative to the gripper); "
        "the shipped recipe: 86/120 against 63/120 without it")))
    release_input: bool = field(default=False, metadata=spec(doc=(
        "export only: obs_encoder.onnx also takes `release_point` (B, 4: a base-frame point in metres and a 0/1 "
        "flag that puts it in place of the head's release point) and returns the head's `aux_points`, for the "
        "goal query (policy/goal_query.py); needs aux_condition and aux_release_frame base. Training ignores it")))
    grasp_input: bool = field(default=False, metadata=spec(doc=(
        "export only: obs_encoder.onnx also takes `grasp_point` (B, 4: a base-frame point in metres and a 0/1 flag "
        "that puts it in place of the head's grasp point, turned relative to the gripper in the graph), for the "
        "object query (policy/object_query.py); needs release_input. Training ignores it")))
    aux_grasp_axis: bool = field(default=False, metadata=spec(doc=(
        "the aux head also regresses the grasp's axis relative to the gripper's yaw, (cos 2d, sin 2d), (0, 0) "
        "for objects without one axis (policy/grasp_axis.py), so the encoder learns which way a bar lies; with "
        "aux_condition the denoiser reads it too (needs aux_target_frame tcp; views rendered with grasp yaws)")))
    aux_condition_source: str = field(default="truth", metadata=spec(choices=("truth", "head"), doc=(
        "what training feeds the denoiser as the aux points: truth (the recorded points plus "
        "aux_condition_noise: teacher forcing, for a head still learning) or head (the head's own prediction, "
        "detached: what inference feeds, so the denoiser learns how far to trust each point; for a frozen, "
        "pretrained head whose release point is poor where pretraining never looked; on the demo recipe it "
        "changed nothing: 27/60 either way)")))
    aux_condition_noise: float = field(default=0.1, metadata=spec(0.0, 10.0, doc=(
        "std of the Gaussian noise on the true points fed in training, in the head's units (tcp frame: "
        "0.25 m per unit), so the denoiser learns to follow a point about as wrong as the head's")))
    aux_release_noise: float | None = field(default=None, metadata=spec(0.0, 10.0, doc=(
        "the same std for the release point alone (None: aux_condition_noise). Why apart: the denoiser follows a "
        "point only as far as training's noise lets it trust it (0.1 = 2.5 cm a side: a 3 cm move of the release "
        "point moves the chunk 1.5-1.8 cm), and a goal query's point can be better than the head's grasp point. "
        "Measured (policy/EXPERIMENTS.md, \"Stack's placing\"): a fine-tune at 0.02 "
        "follows 0.7 of a move, at 0.1 0.5, and both stack 55 of 100")))
    release_point: str = field(default="tcp", metadata=spec(choices=("tcp", "object"), doc=(
        "what the recorded release point is: tcp (where the TCP let go) or object (that point moved by where the "
        "placed object sat in the hand, the episode meta's release_offsets, horizontally: where the object "
        "goes; episodes recorded without them keep the TCP's). With object, an episode whose grasp closed off "
        "centre tells the denoiser the object's goal while its actions let go beside it: to land the object it "
        "must read the hand from the wrist camera (datagen/release_offsets.py); needs aux_target_frame tcp")))
    grasp_noise_windows: str = field(default="all", metadata=spec(choices=("all", "after_grasp"), doc=(
        "which windows of an episode recorded with grasp noise (meta grasp_noise_cm: its grasps closed off the "
        "plan on purpose) train: all, or only those from the first grasp's settled hold on (the off-centre hold "
        "and the place after it, never the approach that closed off centre), so that with release_point object "
        "such episodes teach landing a block held off centre and not closing off centre. Measured (s49, "
        "policy/EXPERIMENTS.md): the fine-tune's grasps were as sloppy without those closes as with them")))
    image_cond_dropout: float = field(default=0.0, metadata=spec(0.0, 1.0, doc=(
        "share of training samples whose image features are hidden from the denoiser (zeroed in its cond; the "
        "aux head still reads them), so it must act on the aux points; 1 = never shown, at inference too: a "
        "points-and-proprio policy whose only view of the scene is the head's grasp and release points "
        "(needs aux_condition)")))
    freeze_pretrained: bool = field(default=False, metadata=spec(doc=(
        "keep the image encoders and the aux head as the warm start left them (sudd train --init-from a `sudd "
        "pretrain` run: what thousands of rendered scenes taught them), so a few hundred episodes cannot turn "
        "them into a lookup of those scenes; the rest trains, and a CPU step skips the encoders' backward "
        "(train_aux_head lets the aux head train too)")))
    train_aux_head: bool = field(default=False, metadata=spec(doc=(
        "with freeze_pretrained: the aux head trains on the episodes anyway (the image encoders stay frozen), "
        "so it learns the points on frames pretraining never showed, such as the release point while the "
        "object is carried")))
    feature_cache: int = field(default=0, metadata=spec(0, 64, doc=(
        "with freeze_pretrained: run the frozen image encoders once over every training frame, for this many "
        "copies (the first uncropped and unjittered, the others with the training crop and jitter), and train "
        "the rest on those features instead of images: the encoders' forward pass and the image reads leave "
        "the training step; 0 = encode every batch")))
    action_frame: str = field(default="base", metadata=spec(choices=("base", "tcp"), doc=(
        "frame the policy learns its chunks in: base (absolute targets) or tcp (relative to the gripper at "
        "the chunk's newest observation, see policy.action_frame); the bundle always emits absolute targets")))
    val_fraction: float = field(default=0.0, metadata=spec(0.0, 0.5, doc=(
        "share of the successful episodes kept out of training (whole episodes, chosen by a hash of task "
        "and seed, so resuming keeps the split) to measure how the model does on scenes it never saw")))
    val_every: int = field(default=500, metadata=spec(1, 10**8, doc="steps between validations"))
    color_jitter: float = field(default=0.2, metadata=spec(0.0, 1.0, doc="brightness/contrast/saturation +-"))
    # optimisation
    batch_size: int = field(default=64, metadata=spec(1, 4096, doc="per process"))
    lr: float = field(default=1e-4, metadata=spec(0.0, 1.0))
    weight_decay: float = field(default=1e-6, metadata=spec(0.0, 1.0))
    betas: tuple[float, float] = field(default=(0.95, 0.999), metadata=spec(0.0, 1.0))
    warmup_steps: int = field(default=500, metadata=spec(0, 10**7))
    grad_clip: float = field(default=1.0, metadata=spec(0.0, 1e6, doc="max grad norm; 0 = off"))
    ema_power: float = field(default=0.75, metadata=spec(0.0, 1.0))
    ema_max_decay: float = field(default=0.9999, metadata=spec(0.0, 1.0))
    amp: bool = False  # bf16 autocast on CUDA
    num_workers: int = field(default=0, metadata=spec(0, 64, doc="DataLoader workers (0 on small machines)"))
    checkpoint_every: int = field(default=1000, metadata=spec(1, 10**8))
    keep_checkpoints: int = field(default=3, metadata=spec(1, 1000))
    log_every: int = field(default=10, metadata=spec(1, 10**6))
    seed: int = field(default=0, metadata=spec(0, 2**31 - 1))

    def validate(self) -> None:
        if self.action_horizon > self.pred_horizon - self.obs_horizon + 1:
            raise ConfigError(f"action_horizon {self.action_horizon} must be <= pred_horizon - obs_horizon + 1 "
                              f"= {self.pred_horizon - self.obs_horizon + 1} (executed actions start at To-1)")
        down = 2 ** (len(self.down_dims) - 1)
        if self.pred_horizon % down:
            raise ConfigError(f"pred_horizon {self.pred_horizon} must be divisible by {down} "
                              f"(the UNet halves it {len(self.down_dims) - 1} times)")
        if len(self.encoder_blocks) != len(self.encoder_widths):
            raise ConfigError("encoder_blocks needs one entry per encoder_widths stage")
        if self.encoder_strides and len(self.encoder_strides) != len(self.encoder_widths):
            raise ConfigError("encoder_strides needs one entry per encoder_widths stage")
        if any(c > s for c, s in zip(self.crop_size, self.image_size)):
            raise ConfigError(f"crop_size {self.crop_size} exceeds image_size {self.image_size}")
        if self.action_frame == "tcp" and self.aux_target_weight > 0 and self.aux_target_frame != "tcp":
            raise ConfigError("action_frame 'tcp' needs aux_target_frame 'tcp' when aux_target_weight > 0 (a "
                              "'base' aux target is read in the absolute actions' normalized units)")
        if self.aux_condition and self.aux_target_weight <= 0:
            raise ConfigError("aux_condition needs aux_target_weight > 0 (the aux head that predicts the points "
                              "it feeds to the denoiser is trained only then)")
        if self.aux_release_frame == "base" and (self.aux_target_weight <= 0 or self.aux_target_frame != "tcp"):
            raise ConfigError(f"aux_release_frame 'base' needs aux_target_weight > 0 and aux_target_frame 'tcp' (got "
                              f"{self.aux_target_weight}, {self.aux_target_frame!r}): it moves only the release "
                              "point of the gripper-frame aux target to the base frame")
        if self.release_input and not (self.aux_condition and self.aux_release_frame == "base"):
            raise ConfigError(f"release_input needs aux_condition = true and aux_release_frame 'base' (got "
                              f"{self.aux_condition}, {self.aux_release_frame!r}): the point it takes replaces "
                              "the base-frame release point the head feeds the denoiser")
        if self.release_point == "object" and (self.aux_target_weight <= 0 or self.aux_target_frame != "tcp"):
            raise ConfigError(f"release_point 'object' needs aux_target_weight > 0 and aux_target_frame 'tcp' (got "
                              f"{self.aux_target_weight}, {self.aux_target_frame!r}): it moves the release point of "
                              "the gripper-frame aux target")
        if self.grasp_input and not self.release_input:
            raise ConfigError("grasp_input needs release_input = true: the object query gives the grasp and the "
                              "release point together, and the obs encoder returns the head's points with them")
        if self.aux_grasp_axis and (self.aux_target_weight <= 0 or self.aux_target_frame != "tcp"):
            raise ConfigError(f"aux_grasp_axis needs aux_target_weight > 0 and aux_target_frame 'tcp' (got "
                              f"{self.aux_target_weight}, {self.aux_target_frame!r}): the axis is relative to the "
                              "gripper, like the tcp frame's points")
        if self.aux_condition_source == "head" and not self.aux_condition:
            raise ConfigError("aux_condition_source 'head' needs aux_condition = true (it says what the denoiser's "
                              "aux inputs are in training)")
        if self.aux_release_noise is not None and not (self.aux_condition and self.aux_condition_source == "truth"):
            raise ConfigError(f"aux_release_noise {self.aux_release_noise} needs aux_condition = true and "
                              f"aux_condition_source 'truth' (got {self.aux_condition}, {self.aux_condition_source!r}): "
                              "it is the noise on the true release point training feeds the denoiser")
        if self.image_cond_dropout > 0 and not self.aux_condition:
            raise ConfigError(f"image_cond_dropout {self.image_cond_dropout} needs aux_condition = true (without "
                              "the aux points a denoiser with hidden images has no view of the scene)")
        if self.train_aux_head and not (self.freeze_pretrained and self.aux_target_weight > 0):
            raise ConfigError("train_aux_head needs freeze_pretrained = true and aux_target_weight > 0 (without "
                              "freezing, the aux head trains anyway)")
        if self.feature_cache and not self.freeze_pretrained:
            raise ConfigError(f"feature_cache {self.feature_cache} needs freeze_pretrained = true (only frozen "
                              "encoders give the same features every step)")
        if self.feature_cache and self.subtask_language_prob > 0:
            raise ConfigError("feature_cache needs subtask_language_prob = 0 (the encoders are FiLMed by the "
                              "instruction, and a cached frame is encoded with its episode's instruction only)")
        if len(set(self.cameras)) != len(self.cameras) or not self.cameras:
            raise ConfigError(f"cameras {self.cameras} must be distinct and non-empty")
        if self.inference_steps > self.num_train_timesteps:
            raise ConfigError("inference_steps cannot exceed num_train_timesteps")
        for w in self.down_dims:
            if w % self.group_norm_groups:
                raise ConfigError(f"down_dims entry {w} is not divisible by group_norm_groups {self.group_norm_groups}")

    @property
    def global_cond_dim(self) -> int:
        """Per observation step: every camera's features + proprio features; the text feature once; last,
        with aux_condition, the aux head's aux_dim outputs."""
        per_step = len(self.cameras) * self.image_feature_dim + self.proprio_feature_dim
        return self.obs_horizon * per_step + self.text_feature_dim + (self.aux_dim if self.aux_condition else 0)

    @property
    def proprio_input_dim(self) -> int:
        """What the proprio encoder reads per step: the normalized proprio, then with stage_bins the stage's one-hot."""
        return self.proprio_dim + self.stage_bins

    @property
    def text_input_dim(self) -> int:
        """The instruction vector the networks read: the sentence's embedding, then with text_goal its goal clause's."""
        return TEXT_DIM * (2 if self.text_goal else 1)

    @property
    def aux_dim(self) -> int:
        """The aux head's outputs: the grasp and release points, then with aux_grasp_axis the axis label."""
        return AUX_DIM + (AXIS_DIM if self.aux_grasp_axis else 0)

    @property
    def aux_noise_std(self) -> tuple[float, ...]:
        """Teacher forcing's noise std per aux input: aux_condition_noise, the release point's 3 aux_release_noise
        where set."""
        std = [self.aux_condition_noise] * self.aux_dim
        if self.aux_release_noise is not None:
            std[3:6] = [self.aux_release_noise] * 3
        return tuple(std)

    def to_dict(self) -> dict:
        return as_dict(self)


_SMALL = PolicyConfig()
_FULL = replace(_SMALL, preset="full", crop_size=(112, 112), encoder_widths=(64, 128, 256, 512),
                encoder_blocks=(2, 2, 2, 2), image_feature_dim=128, proprio_feature_dim=64, text_feature_dim=128,
                down_dims=(256, 512, 1024), kernel_size=5, step_embed_dim=256, batch_size=64, num_workers=4, amp=True,
                checkpoint_every=5000)


def preset(name: str) -> PolicyConfig:
    try:
        return {"small": _SMALL, "full": _FULL}[name]
    except KeyError:
        raise ConfigError(f"unknown policy preset {name!r}; expected one of {list(PRESETS)}") from None


def load_policy_config(spec_: str | Path | PolicyConfig | dict | None = None, overrides: dict | None = None
                       ) -> PolicyConfig:
    """A preset name, a TOML file (its optional `preset` key names the base), an exported bundle's directory
    (the config it was trained with, from its manifest: to fine-tune it), a dict, or a config."""
    if isinstance(spec_, PolicyConfig):
        base, data = spec_, {}
    elif spec_ is None or str(spec_) in PRESETS:
        base, data = preset(str(spec_ or "small")), {}
    elif isinstance(spec_, dict):
        data = dict(spec_)
        base = preset(data.get("preset", "small"))
    elif (Path(spec_) / "manifest.json").is_file():
        import json

        data, base = json.loads((Path(spec_) / "manifest.json").read_text())["config"], preset("small")
        return load_config(PolicyConfig, _merge(data, overrides), where=f"{spec_}/manifest.json", base=base)
    else:
        path = Path(spec_)
        if path.suffix != ".toml":
            raise ConfigError(f"policy config {spec_!r}: expected a preset {list(PRESETS)}, a .toml file or a bundle directory")
        if not path.is_file():
            raise ConfigError(f"policy config file {path} does not exist")
        import tomllib

        data = tomllib.loads(path.read_text())
        base = preset(data.get("preset", "small"))
        return load_config(PolicyConfig, _merge(data, overrides), where=str(path), base=base)
    return load_config(PolicyConfig, _merge(data, overrides), base=base)


def _merge(data: dict, overrides: dict | None) -> dict:
    out = dict(data)
    out.update(overrides or {})
    return out


def config_from_dict(d: dict) -> PolicyConfig:
    """Rebuild a recorded config exactly (an unknown key is an error: the run was made by other code)."""
    return load_config(PolicyConfig, d)
