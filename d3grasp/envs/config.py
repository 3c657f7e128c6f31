"""Configuration of the grasp environment: one dataclass per concern, gathered in GraspEnvConfig.

Everything a task varies lives here, so a task is a ``GraspEnvConfig`` (plus, for training, a
runner config). Times are in seconds and converted to control steps by the environment.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

from d3grasp.kernels.rewards import RewardConfig
from d3grasp.kernels.tactile import TactileConfig
from d3grasp.vocabulary import GRASP_TYPES as VOCABULARY_GRASP_TYPES
from d3grasp.vocabulary import KINDS, SIZE_BINS

ACTION_MODES: tuple[str, ...] = ("residual", "synergy", "absolute")
"""How the actions in [-1, 1] (16, or 4 in synergy mode) become joint targets. ``absolute`` (the paper's):
each action spans its joint's range. ``residual``: the rule-based controller (d3grasp.envs.baseline) runs
inside the environment and each action offsets its joint target by up to ``residual_scale`` rad, so the
zero action is the baseline and learning starts from a hand that already closes on contact. On a 2-core
CPU, PPO from the absolute action space did not reach a single lift in 115k steps (24 minutes), while the
residual space keeps the policy near grasps from the first episode (residual RL). ``synergy``: the
residual mode with one action per finger (4): action f offsets every flexion joint of finger f by the same
amount (a per-finger squeeze, the first postural synergy of a grasp), the abduction joints none. Measured
why: a constant +0.4 rad on every flexion joint from the lift phase on took the rule's train-split lift
rate from 19% to 31%, a change the 4 squeeze actions express; PPO in the 16-joint residual space (3
episodes per iteration on 2 CPU cores) learned that direction but stayed level with the baseline after 800
iterations."""

# The three archetypal grasp types (the paper's directional diversity of 3): top power grasp (palm
# down over the object), side wrap (palm facing the object from the side) and precision pinch
# (index and thumb tips from above); d3grasp.envs.grasps derives their poses.
GRASP_TYPES = VOCABULARY_GRASP_TYPES


@dataclass
class SimConfig:
    """Newton / SolverVBD settings (docs/design.md, Simulation: what holds a grasp on this stack)."""

    control_hz: float = 60.0
    substeps: int = 10  # even; 8 (with collide_every=2) is the fast profile, 4-6 lose most grasps
    iterations: int = 5  # 4 or 3 drop box_01 or push it off the table (measured)
    # SolverVBD iterations of an environment that holds a soft object (docs/design.md, Soft objects
    # under the push). At 5, a FEM body in a fingertip grip is far from converged and behaves much
    # softer than its modulus: 0 of 9 lifted soft objects held 1 s pushes of 2.5 N; at 20, 9 of 15
    # (planned grasps). The cost is ~4x a soft step; the evaluation batches rigid and soft objects
    # apart, so rigid worlds keep ``iterations``.
    soft_iterations: int = 20
    # Chebyshev acceleration of the soft nodes' sweeps (d3grasp.kernels.chebyshev; 0 = plain sweeps).
    # Off: with rho 0.9 neither 10 nor 14 accelerated iterations kept 20 plain ones' holds (docs/design.md,
    # Where a soft step's time goes).
    soft_chebyshev_rho: float = 0.0
    # Of a soft environment's ``soft_iterations``, how many also solve the rigid bodies (the hand, evenly
    # spaced, the last included; 0 = all). The soft nodes need the 20 sweeps; the hand holds rigid
    # objects at 5. 5 of 20: the 20 soft train objects at seeds 0-2 lifted 75.0 against 76.7% (0 / 1
    # pairs) and held 61.7 against 58.3% (4 / 2), the evaluation 0.89x the time (docs/design.md, Where a
    # soft step's time goes).
    soft_rigid_iterations: int = 5
    kinematic_palm: bool = True  # palm prescribed each substep instead of the driven 6-DoF root chain
    collide_every: int = 1  # substeps per collision detection; VBD re-evaluates contacts each iteration
    # Rigid contact capacity per world, pooled over all worlds: a world uses 20-70 contacts, a many-hull
    # object up to ~210 of them (its table and grasp contacts), so the pool covers a few such worlds.
    rigid_contacts_per_world: int = 256
    # SolverVBD's per-body list of body-body contacts (Newton's default 64). A body's contacts beyond it
    # are left out of that body's own solve while the other body still feels them (Newton warns "Per-body
    # rigid contact buffer overflowed"). Objects of many hulls resting on the table or in a grasp reach
    # 207 contacts on the test split (measured with 64: most of them missed); the lists cost only the
    # contacts present, so the buffer is sized well above that.
    body_contact_buffer: int = 384
    use_graph: bool = True  # capture one control step as a Warp graph; False = plain loop (debug)
    # Soft objects' tet elasticity by d3grasp.kernels.fem_elasticity (the same forces and Hessians as
    # SolverVBD's kernel in closed form; False = Newton's kernel, to compare)
    closed_form_tets: bool = True
    # With the closed form on the CPU: each particle iteration adds the nodes' point contacts once
    # instead of once per colour and places the nodes as it solves them (d3grasp.kernels.
    # particle_iteration: the same bits; False = SolverVBD's own iteration, to compare)
    fused_particle_iteration: bool = True
    shape_mu: float = 1.0  # friction of hand and table shapes
    soft_contact_ke: float = 1.0e4
    soft_contact_kd: float = 1.0e-2
    soft_contact_mu: float = 1.0
    soft_contact_gap: float = 0.005
    # m/s, SolverVBD's friction smoothing. Body-body friction forces ignore it (projected Coulomb; it
    # only enters their solve metric while sliding); particle contacts reach full friction only when
    # slipping this fast (a soft puck on the table at half its sliding force: 1.6 mm in 0.5 s at 1e-2,
    # 0.4 mm at 1e-4). 1e-3 held 10 of 24 soft objects through the pushes against 8, and lifted 18
    # against 20 (seed 0, paired 2-0 both ways: docs/history.md, Soft objects), so the default stays.
    friction_epsilon: float = 1.0e-2
    particle_radius: float = 0.003  # m; Newton's default (0.1 m) explodes small objects
    soft_damping: float | None = None  # override every soft object's damping (else the manifest's)
    table_height: float = 0.0  # z of the table surface (m)


@dataclass
class PhaseConfig:
    """Episode schedule: pre-grasp → approach → grasp → lift → hold → disturb (→ release)."""

    approach: float = 0.5  # root moves from pre-grasp to grasp pose
    grasp: float = 1.5  # root still, the fingers close; the lift starts at the latest at its end
    # The lift starts once the pads have felt the object (a thumb pad and an opposing pad, contacts
    # with the object only) for ``grasp_settle`` s without a break: the drives build the squeeze in
    # that time (a joint stopping on touch reaches its squeeze target within ~0.1 s at kd 0.05).
    lift_on_touch: bool = True
    grasp_settle: float = 0.25
    lift: float = 1.0  # root rises lift_height on a smooth (cosine) profile
    hold: float = 0.5
    disturb_per_direction: float = 2.0
    disturb_force: float = 2.5  # N, applied at the object's centre of mass
    train_disturb_directions: int = 1  # training samples this many of the six directions
    release: float = 0.0  # eval: open the hand at the end (not scored)
    lift_height: float = 0.1
    pregrasp_clearance: float = 0.04  # m the palm starts away from its grasp pose


@dataclass
class ObjectSetConfig:
    """Which objects the worlds hold."""

    manifest: str | None = None  # None = the shipped library
    kinds: tuple[str, ...] = KINDS
    split: str = "train"  # train | test | all
    size_bins: tuple[str, ...] = tuple(SIZE_BINS)
    ids: tuple[str, ...] | None = None  # explicit asset ids (overrides the filters above)
    soft_fraction: float = 0.5  # share of worlds given a soft object when both kinds are enabled


@dataclass
class ObservationConfig:
    """What the observation groups hold and the scales that bring each term to O(1) for the
    networks (``d3grasp.envs.mdp.observations`` names the terms). A "per unit" figure divides."""

    action_history: int = 3  # last k actions in the policy observation
    pad_force_per_unit: float = 10.0  # N: pad forces (read and true) / 10
    joint_vel_scale: float = 0.1  # finger joint velocities (rad/s) x 0.1
    palm_offset_scale: float = 10.0  # palm command relative to the grasp pose (m) x 10
    object_offset_scale: float = 10.0  # privileged: object relative to the palm (m) x 10
    object_ang_vel_scale: float = 0.1  # privileged: object angular velocity (rad/s) x 0.1
    link_distance_scale: float = 10.0  # privileged: hand link to object distances (m) x 10
    sigma_scale: float = 100.0  # privileged: the deformable rotation's sigma (m^2) x 100
    log_youngs_per_unit: float = 6.0  # privileged: log10 of Young's modulus (Pa) / 6
    # The episode clock's period (s): t / T, sin and cos of 2 pi t / T with T fixed in seconds, so that
    # training and evaluation read the same clock at the same time. It used to be each environment's
    # own episode length (270 steps in the training recipe, 930 in evaluation), so every trained policy
    # read an unfamiliar clock when evaluated. 4.5 s is the training recipe's episode: the shipped
    # policy was trained with exactly this clock and now reads it in evaluation too.
    clock_period: float = 4.5


@dataclass
class RandomizationConfig:
    """Per-episode domain randomisation (uniform ranges, multiplicative where it says 'scale')."""

    enabled: bool = True
    friction: tuple[float, float] = (0.7, 1.2)
    object_mass_scale: tuple[float, float] = (0.8, 1.2)
    youngs_modulus_scale: tuple[float, float] = (0.7, 1.4)
    object_xy: float = 0.01  # m, uniform in a square of this half-width
    object_yaw: float = 3.14159  # rad, uniform in ±
    tactile_noise_std: float = 0.05  # N
    action_latency_steps: tuple[int, int] = (0, 1)  # control steps
    drive_gain_scale: tuple[float, float] = (0.8, 1.2)


GRASP_SOURCES: tuple[str, ...] = ("file", "rule")
"""Where each object's grasp comes from. ``file``: the library's grasp file (``grasps.json`` next to
its manifest, made by ``d3grasp-assets plan-grasps``: candidates scored in simulation), falling back
to the rule for an object it does not list; ``rule``: the geometric rule on the object's size alone
(``d3grasp.envs.grasps.choose_grasp``)."""

CLOSING_PRIORS: tuple[str, ...] = ("touch", "stall")
"""What stops the rule's closing joints and times the lift (``BaselineConfig.stop_on``). ``touch``: the
pads (the paper's baseline); ``stall``: the joints' own tracking lag, and the lift starts when every
closing joint has stalled: the Base ablation's prior, which reads no touch anywhere."""


PRIOR_SETTINGS: tuple[str, ...] = ("stop_on", "stall_lag")
"""The ``BaselineConfig`` fields that choose the closing prior (``CLOSING_PRIORS``) rather than tune how
a grasp closes; a checkpoint records the kind alone (``RULE_INTERFACE_FIELDS``)."""


@dataclass
class BaselineConfig:
    """The rule-based baseline's settings (``d3grasp.envs.baseline``): also the prior every residual
    policy acts on."""

    close_speed: float = 1.5  # rad/s of joint target per flexion joint
    force_threshold: float = 0.5  # N on a pad stops the joints proximal to it
    squeeze: float = 0.1  # rad added beyond the stopping point (rigid objects)
    # A soft object gives under the pads: at 0.1 rad the grip forms on the few nodes under the
    # fingertips and the pushes tear the body out (docs/design.md, Soft objects under the push).
    # Measured on the 20 soft train objects at seeds 0 and 1 (40 episodes): held through the six
    # pushes 14 at 0.1 rad, 21 at 0.25, 24 at 0.4; lifted 29, 29, 31. On the 104 rigid train objects
    # 0.25 lifted 61 against 81 (a grip closed on touch is an equilibrium that a deeper squeeze
    # breaks), so rigid objects keep 0.1.
    squeeze_deformable: float = 0.4
    per_joint: bool = True  # False: a finger's first touch stops all of its joints
    stop_on: str = "touch"  # see CLOSING_PRIORS
    # rad of target - position that counts as a stalled joint (stop_on stall). Free closing lags
    # ~0.05 rad; chosen on the train split (oracle pose, seed 0, 104 rigid / 20 soft objects), s_lift /
    # s_disturb %: 0.15 -> 25.0 / 22.1 rigid, 70 / 60 soft; 0.3 -> 26.0 / 25.0, 90 / 75; 0.5 -> 30.8 /
    # 28.8, 95 / 80; 0.8 -> 34.6 / 32.7, 100 / 95; 1.2 -> 35.6 / 33.7, 100 / 95 (the touch rule: ~80 / 70
    # rigid). A joint stops once the object has held it back ~0.5 s at close_speed.
    stall_lag: float = 0.8


PERCEPTION_MODES: tuple[str, ...] = ("oracle", "camera")
"""Where the grasp planner gets the object's pose and size. ``oracle``: the simulator's ground truth.
``camera``: an RGB-D camera per world (Newton's ray-traced SensorCamera) and d3grasp.vision's
localisation from its noisy depth image, taken at reset before the hand approaches."""


@dataclass
class CameraConfig:
    """The perception camera of every world and its noise (``GraspEnvConfig.perception = "camera"``)."""

    width: int = 320  # px
    height: int = 240  # px
    fov_deg: float = 50.0  # vertical field of view
    # Nearly straight down: a tilted view hides the far side of round and tapered objects (a bottle's
    # body under its shoulder: 5 mm of centre error at 17 deg of tilt, 1 mm at 4 deg).
    position: tuple[float, float, float] = (0.0, -0.04, 0.6)  # m, world; worlds share the table frame
    target: tuple[float, float, float] = (0.0, 0.0, 0.0)  # m, the point the optical axis goes through
    noise: bool = True  # master switch for the depth noise, dropout and calibration error below
    depth_noise_base: float = 0.0005  # m, depth noise std = base + quadratic * depth**2
    depth_noise_quadratic: float = 0.0025  # m per m^2 (1.3 mm at 0.6 m: active-stereo class)
    dropout: float = 0.02  # fraction of pixels without depth
    calib_pos_std: float = 0.002  # m per axis, camera position error of the extrinsic calibration
    calib_rot_std: float = 0.005  # rad per axis (0.3 deg)
    min_height: float = 0.004  # m above the fitted table plane that counts as object
    # Turn the box fit into the body's pose with the object's own footprint (vision/footprint.py):
    # the planner knows the mesh it planned on, and a fit round a cross, a mug or an L-shape is off
    # its body frame by the same turn and offset every time. False: the fit's centre and yaw as seen.
    register_footprint: bool = True
    # Of the turns whose footprints match alike (a blob's two ends), keep the one whose top surface
    # matches the seen heights (vision/footprint.py). False: the smallest yaw of them, as at first.
    register_heights: bool = True


@dataclass
class GraspEnvConfig:
    num_envs: int = 8
    device: str = "cpu"
    seed: int = 0
    eval_mode: bool = False  # all six disturbance directions, no randomisation of dynamics
    grasp_types: tuple[str, ...] = GRASP_TYPES
    grasp_mode: str = "rule"  # rule: the best type (file) or the size rule; sample: uniform per episode
    grasp_source: str = "file"  # see GRASP_SOURCES
    # rad added to the yaw the grasp is placed at, whatever the pose came from. A study's knob: pi
    # asks whether a grasp is the same grasp on an object turned by its symmetry's half turn, the
    # turn a camera cannot see (docs/studies/camera_registration.md).
    plan_yaw_offset: float = 0.0
    # m (x, y) added to where every world's object is put, the grasp planned at the shifted pose: the
    # whole scene (object and hand together) moved over the infinite table plane, which changes
    # nothing physical. A study's knob for brittleness: an outcome it flips was decided by round-off
    # (``python -m d3grasp.bench shift``; docs/studies/millimetre.md). With the camera, the camera
    # stays where it is (the scene moves under it).
    scene_shift: tuple[float, float] = (0.0, 0.0)
    perception: str = "oracle"  # see PERCEPTION_MODES
    # A registered pose estimator by name (d3grasp.vision.estimators.ESTIMATORS); None: the one
    # perception and camera.register_footprint select (oracle, footprint or box_fit).
    pose_estimator: str | None = None
    rule: BaselineConfig = field(default_factory=BaselineConfig)  # the rule, and the residual's prior
    action_mode: str = "synergy"  # see ACTION_MODES
    # rad of joint-target offset at a residual of 1 (residual, synergy modes). 0.1, the rule's own squeeze
    # beyond the touch: PPO over the planned grasps with 0.4 rad of authority drifted 38 points of train
    # s_lift below the rule by iteration 50, with 0.1 and the penalty below it was level at iteration 75
    # (docs/design.md, Fine-tuning the residual; A residual that pays for leaving the rule).
    residual_scale: float = 0.1
    # Residual mode: the offset applied is a low-pass of the actions, r = b * action + (1 - b) * r
    # (1 = off). Grasp outcomes hinge on contact onsets that a few hundredths of a radian of per-step
    # jitter move (0.04 rad of per-step target noise halved the baseline's lift rate), so step-to-step
    # jitter of the residual (PPO's exploration noise, an untrained policy's output) is filtered while
    # a sustained offset (a firmer squeeze) passes in full within ~10 steps. The rule's own target is
    # not filtered: the zero residual stays exactly the baseline.
    residual_smoothing: float = 0.2
    # Residual as an integrator instead (> 0): r = clip(r + rate * action, -1, 1), a zero action holds the
    # residual. PPO explores with independent per-step noise, which the low-pass averages away: over a
    # 60-step lift the sustained offset it explores has a std of ~0.3 / sqrt(60) of the action noise,
    # so "squeeze harder through the lift" is barely ever tried. Integrated, the same noise is a random
    # walk (std rate * 0.3 * sqrt(n) after n steps): smooth, sustained offsets are what gets explored.
    # 0 (the default): the low-pass above. An integrator explores more, but over the planned grasps, where
    # the rule already lifts ~78%, its random walk broke grasps faster than PPO could learn (measured).
    residual_rate: float = 0.0  # 0.08 reaches a full squeeze in 13 steps
    # Phase from which the residual acts (held at 0 and the actions ignored before it). The approach is
    # scripted and the fingers' pre-shape is the planner's, but an integrating residual active from t = 0
    # turns a small learned bias into a full offset before the first contact: 80 PPO iterations
    # (50 of them updating the actor) gave the thumb a mean action of +0.26 in the approach, and 7 of 16
    # training worlds then ended without a grasp (measured; the rule alone: 2 of 16).
    residual_start: str = "grasp"  # a phase of d3grasp.vocabulary.PHASES; "approach": from t = 0
    action_smoothing: float = 0.5  # target = a * new + (1 - a) * previous target
    # Control steps a decision of the policy is held for (1: a new action every step). The outcome is
    # scored seconds after the fingers close, and what decides it is a sustained offset (a firmer
    # squeeze through the lift), which independent per-step noise through the low-pass barely
    # explores: one step's noise moves the residual by smoothing x noise and is forgotten in ~5 steps.
    # Held for k steps, the exploration noise is a sustained offset, and the policy loss has k times
    # fewer terms, each with k times the effect (the advantage's signal-to-noise up by ~sqrt(k)). The
    # policy still reads every step's touch (its memory runs at 60 Hz); only the actions of decision
    # steps move the fingers, and PPO counts only those (GraspEnv.action_takes_effect). A decision
    # window starts where the actions start to act (residual_start). Residual and synergy modes only:
    # in the absolute mode the actions are the whole controller and act every step.
    decision_steps: int = 10
    # The policy's wrist (residual and synergy modes): 4 more actions, after the fingers', offset the
    # scripted palm path by up to palm_offset_limit m along each world axis and palm_yaw_limit rad about
    # the vertical, from the approach through the lift (held from the hold on), so touch can correct
    # where the camera placed the grasp (5.8 mm mean centre error, 11 mm p95, yaw errors up to 0.77 rad
    # on symmetric-looking objects: docs/evaluation.md, Perception). The offset moves towards
    # action x limit at no more than palm_offset_rate m/s and palm_yaw_rate rad/s, and the zero action
    # is the scripted path, the rule. 0 limits: no wrist (the shipped policy moves the fingers only).
    palm_offset_limit: float = 0.0
    palm_yaw_limit: float = 0.0
    palm_offset_rate: float = 0.02
    palm_yaw_rate: float = 0.3
    privileged_obs: bool = True  # asymmetric critic input group
    tactile_obs: bool = True  # False for the proprioception-only ablation
    sim: SimConfig = field(default_factory=SimConfig)
    phases: PhaseConfig = field(default_factory=PhaseConfig)
    objects: ObjectSetConfig = field(default_factory=ObjectSetConfig)
    obs: ObservationConfig = field(default_factory=ObservationConfig)
    randomization: RandomizationConfig = field(default_factory=RandomizationConfig)
    # Contact and stability weights scaled so a step's terms are O(0.1-1) in this simulator: random
    # finger motion presses pads against the table at tens of newtons and flicks light objects at
    # ~1 m/s, which with the kernel defaults gave per-step rewards of -20 to -40 and returns of -2000.
    # Then re-weighted so the return ranks a lift above a gentle failed grasp. Measured on the 15 test
    # objects (training mode, seed 5): the rule alone lifted 1/15 with a mean return of -30; the rule
    # plus a constant 0.4 rad squeeze lifted 4/15 but returned -171 under contact_penalty 0.05 /
    # max_force 10 N (-71), stability_lin 0.2 (-66) and symmetry 0.5 (-36) against +44 of lift (k_l 1):
    # PPO was being taught not to grip. With f_m 20 N, k_p 0.02, k_ov 0.1, k_s 0.2 and k_l 3 a held
    # object is worth ~+450 over lift, hold and the training push.
    rewards: RewardConfig = field(
        default_factory=lambda: RewardConfig(
            contact_gain=0.02,
            contact_penalty=0.02,
            max_force=20.0,
            symmetry=0.2,
            stability_lin=0.1,
            stability_ang=0.01,
            lift=3.0,
            # The generic term's ||q - q_ref||^2 with q_ref never written (zeros) charged a closed hand
            # ~0.16 per step (16 joints near 1 rad): a cost on gripping. The rule's targets are the
            # reference posture here, and leaving them is what residual_penalty charges: k_j off.
            joint_pos=0.0,
        )
    )
    # Per-step reward clip (0: off). A soft body that blows up or an object flung at metres per second
    # gave single steps of -1e3 to -1e5 (distance and stability terms): one such step made the value
    # loss jump from ~1e2 to ~5e5 and undid the critic. Real grasp steps stay within +-10. The
    # per-term logs are unclipped.
    reward_clip: float = 10.0
    # Residual modes: -k * sum_j r_j^2 per step, r the offset from the rule's targets in [-1, 1] per
    # joint (0: off). Every fine-tuning run over the planned grasps drifted below the rule that its
    # zero action is (docs/design.md, Fine-tuning the residual): with no term that prefers the rule,
    # PPO's noisy updates move the mean offset and the rule's equilibrium grip is lost. This term
    # makes the rule the default that an offset has to pay for.
    residual_penalty: float = 0.02
    # Added to the reward of an episode's last step, per success the scoring gives it (s_lift, s_disturb).
    # The dense terms barely see s_disturb: the lift term reads the object's absolute rise, so a slip of
    # 2 cm under the push (an s_disturb failure) costs a few tenths of a point of return against ~+450
    # for a held object. These terms are what is scored, counted exactly as the metric counts it
    # (d3grasp.kernels.scoring). Not clipped by ``reward_clip`` (a terminal outcome, not a blow-up).
    success_bonus_lift: float = 50.0
    success_bonus_disturb: float = 100.0
    tactile: TactileConfig = field(default_factory=TactileConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)


POLICY_INTERFACE: tuple[str, ...] = (
    "action_mode",
    "residual_scale",
    "residual_smoothing",
    "residual_rate",
    "residual_start",
    "action_smoothing",
    "decision_steps",
    "palm_offset_limit",
    "palm_yaw_limit",
    "palm_offset_rate",
    "palm_yaw_rate",
)
"""The settings that turn a policy's actions into joint targets. A checkpoint only means what it
learned under the values it was trained with, and most of them leave every size unchanged (a
residual_rate of 0.08 against 0 reads and writes the same tensors), so checkpoints record them and
loading one into an environment with other values is refused rather than silently run."""


# The key of a policy interface that holds the observation settings (``ObservationConfig``, by field).
# A changed scale (or the clock's period) leaves every observation size the same and changes what the
# policy sees, so they are recorded and checked like the action settings above.
OBSERVATION_INTERFACE = "obs"

# The key that holds the prior's kind (``BaselineConfig.stop_on``): a residual's zero action is the
# rule, so a policy trained on the stall prior (Base, which reads no touch) run on the touch rule would
# read the pads through its prior. The rule's tuning (squeeze depths, speeds) is not recorded: shipped
# checkpoints are evaluated with today's tuning, which has been re-measured under them (docs/design.md).
RULE_INTERFACE = "rule"
RULE_INTERFACE_FIELDS: tuple[str, ...] = ("stop_on",)

# What a checkpoint recorded before a POLICY_INTERFACE setting existed: the behaviour it was trained with.
# The observation settings are those of the checkpoints from before their record (the shipped mixed_v0
# among them): the defaults of then, written out rather than read from ObservationConfig, so that a
# later change of a default refuses those checkpoints instead of feeding them other scales.
POLICY_INTERFACE_BEFORE: dict[str, object] = {
    "residual_start": "approach",
    "decision_steps": 1,
    "palm_offset_limit": 0.0,
    "palm_yaw_limit": 0.0,
    "palm_offset_rate": 0.02,
    "palm_yaw_rate": 0.3,
    OBSERVATION_INTERFACE: {
        "action_history": 3,
        "pad_force_per_unit": 10.0,
        "joint_vel_scale": 0.1,
        "palm_offset_scale": 10.0,
        "object_offset_scale": 10.0,
        "object_ang_vel_scale": 0.1,
        "link_distance_scale": 10.0,
        "sigma_scale": 100.0,
        "log_youngs_per_unit": 6.0,
        "clock_period": 4.5,
    },
    # Every checkpoint from before this record was trained on the touch rule except the Base task's
    # written from c18d3ec (2026-12-06, when the Base task took stop_on="stall") to e893d0d: the
    # shipped one was given its record; another of those needs the same record written into its
    # infos (docs/training.md), or it is refused on the Base task and evaluated on the touch rule.
    RULE_INTERFACE: {"stop_on": "touch"},
}


def policy_interface(cfg: GraspEnvConfig) -> dict[str, object]:
    """The ``POLICY_INTERFACE`` values of ``cfg``, its observation settings under
    ``OBSERVATION_INTERFACE`` and its prior's kind under ``RULE_INTERFACE`` (what a checkpoint records
    and is checked against)."""
    return {key: getattr(cfg, key) for key in POLICY_INTERFACE} | {
        OBSERVATION_INTERFACE: asdict(cfg.obs),
        RULE_INTERFACE: {key: getattr(cfg.rule, key) for key in RULE_INTERFACE_FIELDS},
    }
