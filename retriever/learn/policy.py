"""Learned policies as flows: a LeRobot checkpoint (:class:`LeRobotPolicy`) or a plain torch
module (:class:`TorchPolicy`), loaded from a local directory in ``setup()``, run on each tick.

A policy flow is a subclass that names its input ports and hands them to :meth:`PolicyFlow.act`::

    class Pick(LeRobotPolicy):
        def step(self, image: np.ndarray | None = None, state: np.ndarray | None = None):
            return self.act(image=image, state=state)

    policy = Pick("runs/act-pick", device="cpu").configure(latency=0.1) @ Rate(hz=5)
    policy.then(controller, sync=ActionChunking(control_hz=200), map={"chunk": "action"})

``act`` builds the observation under the feature keys of :mod:`retriever.features` (those
``retriever log export --format lerobot`` writes), runs the model and returns ``{"chunk": rows}``
(``predict_action_chunk``, for an ``ActionChunking`` edge) or ``{"action": row}``
(``select_action``); ``None`` (no event) while an input is still ``None``.

Replay: on the CPU the flow fixes torch's threads, turns on deterministic algorithms and seeds
each call from its own count, so ``retriever replay`` re-runs it bit for bit. On a GPU it declares
``replay="log"``: GPU kernels' floats depend on the device, driver and the kernels chosen at
run time, and the machine that replays may have no GPU; the replay then takes its chunks from the
log and checks everything downstream of it.

Nothing is fetched from a hub: the path must be a local directory, loading is
``local_files_only``, the Hugging Face hub's offline mode is on (``HF_HUB_OFFLINE=1``, and
``huggingface_hub``'s own switch, which it reads at import, even if it was imported first), and a backbone the
config would download (``pretrained_backbone_weights``) is not: the checkpoint holds its weights.
Nothing in a checkpoint is unpickled or imported: weights are safetensors, configs JSON, and a
processor file whose steps name a class to import (rather than LeRobot's registry) is refused.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from ..clocks import Rate
from ..flow import Flow
from ..flow.core import flow_spec, settings_of
from .features import ObservationFeatures
from .rtc import ChunkTimeline, Leftover

OUTPUTS = ("chunk", "action")
PROCESSORS = ("policy_preprocessor.json", "policy_postprocessor.json")
WEIGHTS = "model.safetensors"
_DEVICE = re.compile(r"cpu|cuda(:\d+)?")


class PolicyFlow(Flow):
    """What :class:`LeRobotPolicy` and :class:`TorchPolicy` share: parameters, the observation,
    the device, determinism and real-time chunking. Subclass one of those two, not this.

    - ``path``: the local checkpoint directory.
    - ``device``: ``"cpu"`` or ``"cuda"`` (``"cuda:N"``).
    - ``features``: source (an input, or ``input.field``) → feature key, where the convention of
      :mod:`retriever.features` does not fit (the export's ``--map``).
    - ``output``: ``"chunk"`` (emit the whole chunk on port ``chunk``) or ``"action"`` (one row on
      port ``action``).
    - ``threads``: torch's CPU threads (process-wide; fixed so that replay repeats the floats).
    - ``seed``: the model's randomness at call ``n`` is seeded with ``seed + n`` (diffusion noise).
    - ``rtc``, ``control_hz``, ``control_offset``, ``chunk_hz``: real-time chunking, below.

    With ``rtc=True`` the flow knows, at each tick, what its controller (on
    ``Rate(control_hz, offset=control_offset)``, behind ``ActionChunking(control_hz=chunk_hz)``)
    executes of its earlier chunks until the new one takes over (:mod:`retriever.learn.rtc`):
    :attr:`leftover` holds it during the tick; the new chunk is emitted from its row ``delay`` on
    (the rows before it fall in the time the old chunk still plays, as LeRobot's RTC queue drops
    them), and a LeRobot policy whose config enables RTC gets ``prev_chunk_left_over`` and
    ``inference_delay``. It reads its tick's time from its count of ticks, so it must be stepped at
    every tick of its ``Rate`` clock: every port has a default (or is Optional), ``on_overrun=
    "catch_up"``, no ``on_error="restart"``, and ``step`` calls ``act`` once. ``setup()`` checks
    the first three.

    ``act``'s keywords are the step's input ports, unless the class names others in
    :attr:`observation` (a step that takes a message apart: ``act(image=frame.rgb, state=obs.robot)``).
    """

    #: the names ``act()`` takes, each mapped to a feature key; None: the step's input ports
    observation: tuple[str, ...] | None = None

    def __init__(self, path: str, device: str = "cpu", features: dict[str, str] | None = None,
                 output: str = "chunk", threads: int = 1, seed: int = 0, rtc: bool = False,
                 control_hz: float | None = None, control_offset: float = 0.0, chunk_hz: float | None = None):
        owner = type(self).__qualname__
        problems = []
        if not isinstance(path, str) or not path:
            problems.append(f"path={path!r} must be the checkpoint directory, as a str")
        if not isinstance(device, str) or not _DEVICE.fullmatch(device):
            problems.append(f"device={device!r} must be 'cpu', 'cuda' or 'cuda:N'")
        if output not in OUTPUTS:
            problems.append(f"output={output!r} must be 'chunk' (predict_action_chunk) or 'action' (select_action)")
        if type(threads) is not int or threads < 1:
            problems.append(f"threads={threads!r} must be an integer >= 1")
        if type(seed) is not int or seed < 0:
            problems.append(f"seed={seed!r} must be an integer >= 0")
        if rtc and output != "chunk":
            problems.append("rtc=True needs output='chunk': real-time chunking joins chunks")
        if rtc and control_hz is None:
            problems.append("rtc=True needs control_hz, the rate of the controller that plays the chunks")
        if features is not None and not isinstance(features, dict):
            problems.append(f"features={features!r} must be a dict of port -> feature key")
        if problems:
            raise ValueError(f"{owner}: " + "\n    ".join(problems))
        if rtc:
            ChunkTimeline(control_hz, chunk_hz=chunk_hz, control_offset=control_offset)  # checks the rates now
        names = tuple(flow_spec(type(self)).inputs) if self.observation is None else tuple(self.observation)
        self.observed = ObservationFeatures(owner, names, features)
        self.path, self.device, self.features, self.output = path, device, features, output
        self.threads, self.seed, self.rtc = threads, seed, rtc
        self.control_hz, self.control_offset, self.chunk_hz = control_hz, control_offset, chunk_hz
        self.timeline: ChunkTimeline | None = None  # rtc: made at the first tick, with the latency then configured
        #: real-time chunking: what the controller plays of earlier chunks from this tick on
        self.leftover: Leftover | None = None
        self.ticks = 0  # act() calls: the tick count rtc reads its time from
        self.calls = 0  # model calls: each one's seed
        self.raw_chunks: dict[int, Any] = {}  # rtc: each kept chunk's rows as the model made them
        if device != "cpu":
            self.configure(replay="log")

    # -- lifecycle ------------------------------------------------------------------------
    def setup(self) -> None:
        import torch

        owner = self._owner()
        if self.device.startswith("cuda") and not torch.cuda.is_available():
            raise RuntimeError(f"{owner}: device={self.device!r}, but torch {torch.__version__} finds no CUDA device "
                               f"(built with CUDA {torch.version.cuda or 'none'})\n    hint: device='cpu'")
        if self.rtc:
            self._check_rtc()
        if self.device == "cpu":
            torch.set_num_threads(self.threads)
            torch.use_deterministic_algorithms(True)
        #: feature key -> the shape the model takes; None where the checkpoint does not say (TorchPolicy)
        self.shapes: dict[str, tuple[int, ...]] | None = None
        self.model = self._load(self._directory())

    def teardown(self) -> None:
        for name in ("model", "preprocess", "postprocess"):
            self.__dict__.pop(name, None)
        if self.device.startswith("cuda"):
            import torch

            torch.cuda.empty_cache()

    def reset(self) -> None:
        super().reset()
        model = self.__dict__.get("model")
        if model is not None and hasattr(model, "reset"):
            model.reset()  # LeRobot policies queue actions between select_action calls

    # -- a tick ---------------------------------------------------------------------------
    def act(self, **values: Any) -> dict[str, np.ndarray] | None:
        """Run the model on this tick's port values: ``{"chunk": rows}`` or ``{"action": row}``,
        or None while a port's value is None."""
        tick = self.ticks
        self.ticks += 1
        if self.rtc:
            if self.timeline is None:
                self.timeline = ChunkTimeline(self.control_hz, latency=settings_of(self).latency,
                                              chunk_hz=self.chunk_hz, control_offset=self.control_offset)
            self.leftover = self.timeline.leftover(settings_of(self).clock.tick_time(tick))
        names = self.observed.names
        if values.keys() != set(names):
            raise ValueError(f"{self._owner()}.act() takes {', '.join(names)}; got {', '.join(values) or 'nothing'}"
                             "\n    hint: name act()'s keywords in the class's observation = (...)")
        if any(v is None for v in values.values()):
            return None
        import torch

        if "model" not in self.__dict__:
            raise RuntimeError(f"{self._owner()}: no model loaded: setup() has not run\n    hint: a runtime calls "
                               "setup() before the first tick; outside one, call policy.setup() first")
        arrays = self.observed(values)
        self._check_shapes(arrays)
        observation = {key: torch.from_numpy(array) for key, array in arrays.items()}
        with torch.random.fork_rng(devices=[]), torch.no_grad():
            torch.manual_seed(self.seed + self.calls)
            self.calls += 1
            raw, out = self._run(observation)
        if not np.isfinite(out).all():
            raise ValueError(f"{self._owner()}: its model's output is not finite (NaN or infinity in "
                             f"{int((~np.isfinite(out)).sum())} of {out.size} values): nothing is sent to the "
                             "actuators\n    hint: check the checkpoint's weights")
        if self.output == "action":
            return {"action": out.reshape(-1)}
        if self.timeline is None:
            return {"chunk": out}
        return {"chunk": self._joined(tick, raw, out)}

    def _joined(self, tick: int, raw: Any, rows: np.ndarray) -> np.ndarray:
        """The new chunk from the row the controller first plays; remembered on the timeline."""
        delay = self.leftover.delay
        if delay >= len(rows):
            raise ValueError(f"{self._owner()}: its chunk of {len(rows)} rows is over before it plays: the controller "
                             f"plays {delay} rows of the previous chunk until the new one arrives\n    hint: a longer "
                             "chunk, a lower latency, or rtc=False")
        index = self.timeline.add(settings_of(self).clock.tick_time(tick), len(rows) - delay)
        self.raw_chunks[index] = raw[delay:]
        kept = {chunk.index for chunk in self.timeline.chunks}
        self.raw_chunks = {i: r for i, r in self.raw_chunks.items() if i in kept}
        return rows[delay:]

    def leftover_rows(self) -> Any:
        """The rows of :attr:`leftover`, as the model made them (a LeRobot policy's, normalized):
        a ``(len(rows), action_dim)`` tensor, or None when no chunk plays yet."""
        import torch

        if not self.leftover or not self.leftover.rows:
            return None
        return torch.stack([self.raw_chunks[chunk][row] for chunk, row in self.leftover.rows])

    # -- helpers --------------------------------------------------------------------------
    def _owner(self) -> str:
        name = settings_of(self).name
        return f"{type(self).__qualname__} {name!r}" if name else type(self).__qualname__

    def _directory(self) -> Path:
        path = Path(self.path)
        if not path.is_dir():
            raise FileNotFoundError(f"{self._owner()}: {self.path!r} is not a local checkpoint directory (nothing is "
                                    "fetched from a hub)\n    hint: download or train the checkpoint first, and give "
                                    "the directory that holds its weights")
        return path

    def _check_shapes(self, arrays: dict[str, np.ndarray]) -> None:
        """The observation's features are the model's, each of the shape it was trained on."""
        if self.shapes is None:
            return
        sources = {key: source for source, key in (self.observed.keys or {}).items()}
        problems = [f"the policy takes {key!r}, which the observation has no feature for"
                    for key in sorted(self.shapes.keys() - arrays.keys())]
        problems += [f"{sources[key]!r} gives feature {key!r}, which the policy does not take"
                     for key in arrays.keys() - self.shapes.keys()]
        problems += [f"{sources[key]!r} gives feature {key!r} the shape {array.shape}; the policy was trained on "
                     f"{self.shapes[key]}" for key, array in arrays.items()
                     if key in self.shapes and array.shape != self.shapes[key]]
        if problems:
            raise ValueError(f"{self._owner()}: its observation does not fit the checkpoint's input features "
                             f"({', '.join(sorted(self.shapes))}):\n    " + "\n    ".join(problems)
                             + "\n    hint: features={'source': 'feature key'}, or name the inputs after the features")

    def _check_rtc(self) -> None:
        settings, spec = settings_of(self), flow_spec(type(self))
        problems = []
        if not isinstance(settings.clock, Rate):
            problems.append(f"its clock is {settings.clock!r}; rtc counts the ticks of a Rate clock")
        required = [name for name, port in spec.inputs.items() if port.required]
        if required:
            problems.append(f"port(s) {', '.join(required)} have no default, so a tick without them is skipped "
                            "uncounted: give each a default (= None)")
        if settings.on_overrun != "catch_up":
            problems.append(f"on_overrun={settings.on_overrun!r} skips ticks late in real time: "
                            "configure(on_overrun='catch_up')")
        if settings.on_error == "restart":
            problems.append("on_error='restart' starts its tick count again: use 'stop' or 'skip_tick'")
        if problems:
            raise ValueError(f"{self._owner()}: rtc=True reads each tick's time from its count of ticks, which "
                             "needs every tick stepped:\n    " + "\n    ".join(problems))

    def _load(self, path: Path) -> Any:
        raise NotImplementedError

    def _run(self, observation: dict) -> tuple[Any, np.ndarray]:
        """(the model's rows as it made them, the rows to emit as float32 numpy)."""
        raise NotImplementedError


def hub_offline() -> None:
    """Turn the Hugging Face hub's offline mode on: nothing goes to a hub. ``huggingface_hub``
    reads ``HF_HUB_OFFLINE`` once, at its import, and keeps an HTTP session per thread made by
    it: the environment alone is too late if it was imported before, so its switch is set and its
    sessions remade (each then refuses any request with OfflineModeIsEnabled)."""
    os.environ["HF_HUB_OFFLINE"] = "1"
    from huggingface_hub import constants
    from huggingface_hub.utils import reset_sessions

    if not constants.HF_HUB_OFFLINE:
        constants.HF_HUB_OFFLINE = True
        reset_sessions()


@contextlib.contextmanager
def _temporary_files_removed():
    """Python's temporary files made meanwhile go to a folder of their own, removed after: LeRobot's
    ``PreTrainedConfig.from_pretrained`` writes the config it parses to a temporary file it never
    removes (``NamedTemporaryFile(delete=False)``), one more in the machine's /tmp per load. The
    folder is the process's for that while (``tempfile.tempdir``): a policy loads in its flow's
    setup, before its run's threads make files of their own."""
    with tempfile.TemporaryDirectory(prefix="retriever-lerobot-") as folder:
        before, tempfile.tempdir = tempfile.tempdir, folder
        try:
            yield
        finally:
            tempfile.tempdir = before


class LeRobotPolicy(PolicyFlow):
    """A LeRobot ``PreTrainedPolicy`` checkpoint directory (``config.json``, ``model.safetensors``,
    and, as ``lerobot-train`` writes them, its pre/post-processors: normalization). Its config's
    ``input_features`` must be exactly the observation's features. See :class:`PolicyFlow`."""

    def _load(self, path: Path) -> Any:
        hub_offline()
        from lerobot.configs.policies import PreTrainedConfig
        from lerobot.policies.factory import get_policy_class

        try:
            with _temporary_files_removed():
                config = PreTrainedConfig.from_pretrained(path, local_files_only=True)
        except Exception as e:
            raise ValueError(f"{self._owner()}: {path / 'config.json'} is no LeRobot policy config that this lerobot "
                             f"reads ({type(e).__name__}: {str(e)[:300]})\n    hint: give the directory "
                             "lerobot-train or save_pretrained wrote") from None
        config.device = self.device
        if getattr(config, "pretrained_backbone_weights", None) is not None:
            config.pretrained_backbone_weights = None  # the checkpoint holds the backbone's trained weights
        self.shapes = {key: tuple(feature.shape) for key, feature in config.input_features.items()}
        policy = get_policy_class(config.type).from_pretrained(path, config=config, local_files_only=True, strict=True)
        policy.to(self.device).eval()
        self.preprocess, self.postprocess = self._processors(path)
        rtc = getattr(config, "rtc_config", None)
        self.takes_leftover = rtc is not None and getattr(rtc, "enabled", False)
        return policy

    def _processors(self, path: Path) -> tuple[Any, Any]:
        present = [(path / name).is_file() for name in PROCESSORS]
        if not any(present):
            return None, None
        if not all(present):
            raise FileNotFoundError(f"{self._owner()}: {path} has one of {' and '.join(PROCESSORS)} without the other")
        for name in PROCESSORS:
            _check_registered_steps(self._owner(), path / name)
        from lerobot.processor import PolicyProcessorPipeline
        from lerobot.processor.converters import policy_action_to_transition, transition_to_policy_action

        pre = PolicyProcessorPipeline.from_pretrained(path, config_filename=PROCESSORS[0], local_files_only=True,
                                                      overrides={"device_processor": {"device": self.device}})
        post = PolicyProcessorPipeline.from_pretrained(path, config_filename=PROCESSORS[1], local_files_only=True,
                                                       to_transition=policy_action_to_transition,
                                                       to_output=transition_to_policy_action)
        return pre, post

    def _run(self, observation: dict) -> tuple[Any, np.ndarray]:
        import torch

        if self.preprocess is not None:
            batch = self.preprocess(observation)
        else:
            batch = {key: value.unsqueeze(0).to(self.device) for key, value in observation.items()}
        if self.output == "action":
            raw = self.model.select_action(batch)
        elif self.timeline is not None and self.takes_leftover:
            raw = self.model.predict_action_chunk(batch, inference_delay=self.leftover.delay,
                                                  prev_chunk_left_over=self.leftover_rows())
        else:
            raw = self.model.predict_action_chunk(batch)
        out = raw if self.postprocess is None else self.postprocess(raw)
        return raw[0], out[0].detach().to("cpu", torch.float32).numpy()


def _check_registered_steps(owner: str, path: Path) -> None:
    """Refuse a processor file whose steps are not all LeRobot's registered ones: a step named by
    ``class`` makes LeRobot import the module the file names."""
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
        steps = doc["steps"]
        if type(steps) is not list:
            raise TypeError
    except (OSError, ValueError, KeyError, TypeError):
        raise ValueError(f"{owner}: {path} is no LeRobot processor file (JSON with a list of steps)") from None
    for i, step in enumerate(steps):
        if type(step) is not dict or type(step.get("registry_name")) is not str or "class" in step:
            raise ValueError(f"{owner}: {path}, step {i}, names no registered LeRobot processor step "
                             "(a 'class' to import is refused: nothing a checkpoint names is imported)\n"
                             "    hint: save the processors with LeRobot's registered steps")


class TorchPolicy(PolicyFlow):
    """A plain ``torch.nn.Module``, for policies trained outside LeRobot: the subclass builds the
    module in :meth:`build` (its class is named in code, never by a file) and the weights come
    from ``model.safetensors`` in ``path`` (``safetensors.torch.save_file(module.state_dict(), ...)``),
    loaded strictly. The module is called with the observation as a dict of feature key → tensor
    with a batch dimension of 1 (LeRobot's batch), and returns the chunk ``(1, T, A)`` or ``(T, A)``,
    or one action ``(1, A)`` or ``(A,)``. With ``rtc=True`` it is also given
    ``prev_chunk_left_over`` (the leftover rows, or None) and ``inference_delay`` keywords, as
    LeRobot's RTC policies are. See :class:`PolicyFlow`."""

    def build(self) -> Any:
        """The module, with freshly initialised weights (``setup()`` loads the trained ones)."""
        raise NotImplementedError(f"{type(self).__qualname__} must define build(self) -> torch.nn.Module")

    def _load(self, path: Path) -> Any:
        from safetensors.torch import load_file

        weights = path / WEIGHTS
        if not weights.is_file():
            raise FileNotFoundError(f"{self._owner()}: {path} holds no {WEIGHTS}\n    hint: save the weights with "
                                    f"safetensors.torch.save_file(module.state_dict(), '{path / WEIGHTS}')")
        module = self.build()
        module.load_state_dict(load_file(weights, device="cpu"), strict=True)
        return module.to(self.device).eval()

    def _run(self, observation: dict) -> tuple[Any, np.ndarray]:
        import torch

        batch = {key: value.unsqueeze(0).to(self.device) for key, value in observation.items()}
        if self.timeline is not None:
            raw = self.model(batch, prev_chunk_left_over=self.leftover_rows(), inference_delay=self.leftover.delay)
        else:
            raw = self.model(batch)
        if raw.dim() == (3 if self.output == "chunk" else 2):
            raw = raw[0]
        return raw, raw.detach().to("cpu", torch.float32).numpy()
