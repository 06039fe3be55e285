"""Retriever-0: the planner–monitor–skill–controller agent of the paper (Sec. V, Listing 1) on
the drawer task (and the bag task), as one Retriever graph.

    goal ─▶ planner ◀──request── monitor ◀── belief ◀── head camera ◀── world ◀── controller
              │   ▲                                      │
              │   └──────── frame (a VLM planner) ───────┘
              └──plan──▶ monitor ──skill──▶ skill policy ──chunk (ActionChunking)──▶ controller
                         ▲   ▲                 │  └── inspection_done ──▶ belief
                         │   └──── progress ───┘
                         └── teleop

Every flow declares a latency (logical execution time), so a real-time run on ``zenoh`` that
meets its deadlines produces the same trace as the virtual-time run on ``inproc``. ``build()``
takes only JSON-able options: they go into the IR, from which every backend rebuilds the flows.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

from retriever import ActionChunking, Latest, LatestDistinct, Pipeline, Queue, Rate, Trigger

from .plan import DRAWERS
from .planner import make_planner
from .flows import (
    BeliefUpdater, Camera, Controller, Goal, LearnedSkill, Monitor, PlannerFlow, SkillActor, SkillOrder, SkillPolicy,
    Teleop, World,
)

#: seconds a camera takes to render a frame (its declared latency)
CAMERA_LATENCY = 0.02

ABLATIONS = ("full", "no-plan-chunking", "no-skill-progress", "human-in-the-loop", "vla-only")

#: the skill whose policy is pluggable (``skill_policy``), and the node that runs it
LEARNED_SKILL, LEARNED_SKILL_CALL, POLICY_NODE = "Pick", "Pick(spice)", "pick_policy"


@dataclass
class AgentConfig:
    """What an episode is: the world's seed and the agent's rates, latencies and ablation."""
    seed: int = 0
    task: str = "drawers"            # "drawers" (seasoning with drawers) | "bag" (retrieving from a bag)
    drawer: str | None = None        # where the spice is; None: chosen by the seed
    ablation: str = "full"
    planner: str = "scripted"        # or "openai:<base_url>#<model>"
    planner_latency: float = 2.0     # seconds the planner takes (its declared latency)
    policy_hz: float = 2.0
    policy_latency: float = 0.2
    control_hz: float = 200.0
    camera_hz: float = 10.0
    monitor_hz: float = 10.0
    deadline: float = 0.5            # seconds a tick waits for its inputs before it runs without them
    head_size: tuple = (96, 128)
    wrist_size: tuple = (64, 64)
    slip_prob: float = 0.0           # failure injection: a slipped grasp, decided per seed
    teleop: str | None = None        # a teleop schedule file
    verbose: bool = False            # the monitor prints a line per skill change
    # the Pick skill's policy in its own flow (POLICY_NODE): "scripted" or a checkpoint directory
    # (agents.skill_policies); None: the skill flow runs Pick like every other skill
    skill_policy: str | None = None
    episode: str = "task"            # "task": the whole task; "pick": the Pick skill alone, from where it begins

    def check(self) -> None:
        if self.task not in ("drawers", "bag"):
            raise ValueError(f"unknown task {self.task!r}: choose drawers or bag")
        if self.task == "bag" and self.drawer is not None:
            raise ValueError("--drawer is for the drawers task; the bag task has one bag")
        if self.ablation not in ABLATIONS:
            raise ValueError(f"unknown ablation {self.ablation!r}: choose one of {', '.join(ABLATIONS)}")
        if self.drawer is not None and self.drawer not in DRAWERS:
            raise ValueError(f"unknown drawer {self.drawer!r}: choose {', '.join(DRAWERS)}")
        if type(self.seed) is not int or not 0 <= self.seed < 2**32:
            raise ValueError(f"seed {self.seed!r} must be an integer in [0, 2**32)")
        if self.episode not in ("task", "pick"):
            raise ValueError(f"unknown episode {self.episode!r}: choose task or pick")
        if self.task == "bag" and (self.skill_policy is not None or self.episode != "task"):
            raise ValueError("a skill policy (and a Pick-only episode) is for the drawers task")
        if self.skill_policy is not None:
            from .skill_policies import check_skill_policy
            check_skill_policy(self.skill_policy)
        if not 0 <= self.slip_prob <= 1:
            raise ValueError(f"slip probability {self.slip_prob!r} must be in [0, 1]")
        make_planner(self.planner, self.task)  # a planner it cannot make is refused before anything starts
        for name in ("planner_latency", "policy_latency", "deadline"):
            if not 0 < getattr(self, name) <= 60:
                raise ValueError(f"{name}={getattr(self, name)!r} must be in (0, 60] seconds")


def build(config: AgentConfig | None = None, **options) -> Pipeline:
    """The Retriever-0 graph for one episode (``options`` override ``config``'s fields)."""
    config = AgentConfig(**{**(asdict(config) if config else {}), **options})
    config.check()
    if config.episode == "pick":
        return _pick_episode(config)
    seed, drawer, task = config.seed, config.drawer, config.task
    control_period = 1.0 / config.control_hz
    monitor_options = {
        "full": {},
        "no-plan-chunking": {"chunking": False},
        "no-skill-progress": {"switching": "timeout"},
        "human-in-the-loop": {},
        "vla-only": {},
    }[config.ablation]
    planner, planner_latency = config.planner, config.planner_latency
    if config.ablation == "no-plan-chunking":
        planner = "scripted-one-skill"
    elif config.ablation == "vla-only":       # no planner: one policy, a fixed skill order from the start
        planner, planner_latency = "fixed-order", 0.01

    # a simulated robot: physics and every rate catch up on missed ticks rather than skip them, and a
    # tick waits up to its deadline (half a second) for its inputs, so that a real-time run that keeps up is the
    # virtual-time run, tick for tick (a real robot would rather skip and not wait)
    catch_up = {"on_overrun": "catch_up"}
    with Pipeline(f"retriever0-{task}-{config.ablation}", deadline=config.deadline) as pipe:
        goal = Goal(task=task).named("goal").configure(**catch_up, latency=0.01) @ Rate(1)
        world = World(seed=seed, drawer=drawer, tick=control_period, slip_prob=config.slip_prob, task=task,
                      sensors=config.skill_policy is not None).named("world") \
            .configure(**catch_up, latency=control_period) @ Rate(config.control_hz)
        head = Camera("head", *config.head_size, seed=seed, drawer=drawer, task=task) \
            .named("head_camera").configure(**catch_up, latency=CAMERA_LATENCY) @ Rate(config.camera_hz)
        wrist = Camera("wrist", *config.wrist_size, seed=seed, drawer=drawer, task=task) \
            .named("wrist_camera").configure(**catch_up, latency=CAMERA_LATENCY) @ Rate(config.camera_hz)
        belief = BeliefUpdater(seed=seed, drawer=drawer, task=task).named("belief").configure(latency=0.1) \
            @ Trigger("inspection")
        monitor = Monitor(verbose=config.verbose, task=task, **monitor_options).named("monitor") \
            .configure(**catch_up, latency=0.01) @ Rate(config.monitor_hz)
        skill = SkillPolicy(control_hz=config.control_hz, task=task, actor=_actor(config)).named("skill") \
            .configure(**catch_up, latency=config.policy_latency) @ Rate(config.policy_hz)
        ctrl = Controller(hz=config.control_hz).named("controller").configure(**catch_up, latency=control_period) \
            @ Rate(config.control_hz)

        world.then(head, sync=Latest(), map={"obs": "obs"})
        world.then(wrist, sync=Latest(), map={"obs": "obs"})
        world.then(skill, sync=Latest(), map={"obs": "obs"})
        world.then(monitor, sync=Latest(), map={"obs": "obs"})
        world.then(belief, sync=Latest(), map={"obs": "obs"})
        head.then(belief, sync=Latest(), map={"frame": "frame"})
        head.then(skill, sync=Latest(staleness=0.5), map={"frame": "frame"})
        skill.then(ctrl, sync=ActionChunking(control_hz=config.control_hz), map={"chunk": "action"})
        ctrl.then(world, sync=Latest(), map={"command": "command"})
        skill.then(monitor, sync=Queue(maxsize=64), map={"progress": "progress"})
        skill.then(belief, sync=LatestDistinct(), map={"inspection": "inspection"})
        belief.then(monitor, sync=Latest(), map={"belief": "belief"})
        monitor.then(skill, sync=Latest(), map={"skill": "skill"})
        goal.then(monitor, sync=Latest(), map={"task": "task"})
        _plug_policy(config, monitor, world, wrist, ctrl)

        # a model behind an endpoint answers differently tomorrow: a replay takes its answers from the log
        consults_the_world = planner.startswith("openai:")
        plan = PlannerFlow(planner=planner, task=task).named("planner") \
            .configure(latency=planner_latency, replay="log" if consults_the_world else "rerun") @ Trigger("request")
        # a vision-language model looks at the head camera's newest frame, one the camera took at
        # or after the request: the request reaches it a camera period and a render later (the
        # first request comes before the first frame); and it may give up on a request. The
        # scripted planners need none of this, and their graph stays as it was.
        look = 1.0 / config.camera_hz + CAMERA_LATENCY if consults_the_world else 0.0
        goal.then(plan, sync=Latest(), map={"task": "task"})
        monitor.then(plan, sync=LatestDistinct(), map={"request": "request"}, delay=look)
        plan.then(monitor, sync=Queue(maxsize=16), map={"plan": "plan"})
        if consults_the_world:
            head.then(plan, sync=Latest(), map={"frame": "frame"})
            plan.then(monitor, sync=Queue(maxsize=16), map={"failure": "plan_failure"})
        if config.teleop or config.ablation == "human-in-the-loop":
            teleop = Teleop(schedule=config.teleop, recover=config.ablation == "human-in-the-loop", task=task) \
                .named("teleop").configure(**catch_up, latency=0.01, replay="log" if config.teleop else "rerun") \
                @ Rate(config.monitor_hz)
            world.then(teleop, sync=Latest(), map={"obs": "obs"})
            monitor.then(teleop, sync=Latest(), map={"status": "status"})
            teleop.then(monitor, sync=Queue(maxsize=16), map={"teleop": "teleop"})
    return pipe


def _actor(config: AgentConfig) -> str:
    return LEARNED_SKILL if config.skill_policy is not None else ""


def _plug_policy(config: AgentConfig, commander, world, wrist, ctrl) -> None:
    """With a skill policy, its flow: the commanded skill, the world's ``state`` and ``scene``
    and the wrist frame in; while Pick runs, the chunk out to the controller."""
    if config.skill_policy is None:
        return
    if config.skill_policy == "scripted":
        actor = SkillActor(skill=LEARNED_SKILL, control_hz=config.control_hz, policy_hz=config.policy_hz,
                           wrist_size=list(config.wrist_size))
    else:
        actor = LearnedSkill(path=config.skill_policy, skill=LEARNED_SKILL, control_hz=config.control_hz,
                             wrist_size=list(config.wrist_size))
    actor = actor.named(POLICY_NODE).configure(on_overrun="catch_up", latency=config.policy_latency) \
        @ Rate(config.policy_hz)
    commander.then(actor, sync=Latest(), map={"skill": "skill"})
    world.then(actor, sync=Latest(), map={"state": "state", "scene": "scene"})
    wrist.then(actor, sync=Latest(staleness=0.5), map={"frame": "wrist"})
    actor.then(ctrl, sync=ActionChunking(control_hz=config.control_hz), map={"action": "action"})


def _pick_episode(config: AgentConfig) -> Pipeline:
    """The Pick skill alone, from where it begins in the task (the spice's drawer open, the hand
    parked beside it): the world, the wrist camera, the skill flow, the skill's policy flow
    (with ``skill_policy``) and the controller; it ends when the skill says done or failed."""
    from .skills import pick_start
    from .world import Layout
    _, start = pick_start(Layout.from_seed(config.seed, config.drawer))
    control_period = 1.0 / config.control_hz
    catch_up = {"on_overrun": "catch_up"}
    with Pipeline(f"retriever0-{LEARNED_SKILL.lower()}", deadline=config.deadline) as pipe:
        order = SkillOrder(skill=LEARNED_SKILL_CALL).named("order").configure(**catch_up, latency=0.01) \
            @ Rate(config.monitor_hz)
        world = World(seed=config.seed, drawer=config.drawer, tick=control_period,
                      sensors=config.skill_policy is not None, start="pick").named("world") \
            .configure(**catch_up, latency=control_period) @ Rate(config.control_hz)
        wrist = Camera("wrist", *config.wrist_size, seed=config.seed, drawer=config.drawer) \
            .named("wrist_camera").configure(**catch_up, latency=CAMERA_LATENCY) @ Rate(config.camera_hz)
        skill = SkillPolicy(control_hz=config.control_hz, actor=_actor(config)).named("skill") \
            .configure(**catch_up, latency=config.policy_latency) @ Rate(config.policy_hz)
        ctrl = Controller(hz=config.control_hz, home=start.tolist()).named("controller") \
            .configure(**catch_up, latency=control_period) @ Rate(config.control_hz)
        world.then(wrist, sync=Latest(), map={"obs": "obs"})
        world.then(skill, sync=Latest(), map={"obs": "obs"})
        order.then(skill, sync=Latest(), map={"skill": "skill"})
        skill.then(order, sync=Queue(maxsize=64), map={"progress": "progress"})
        skill.then(ctrl, sync=ActionChunking(control_hz=config.control_hz), map={"chunk": "action"})
        ctrl.then(world, sync=Latest(), map={"command": "command"})
        _plug_policy(config, order, world, wrist, ctrl)
    return pipe


#: the paper's episode (the spice in TR), for ``retriever run|deploy agents/retriever0.py:pipe``
pipe = build(drawer="TR")
