"""Planners: the VLM that proposes plan chunks, behind one interface (paper Appendix E-d, E-g, I).

``ScriptedPlanner`` is the default stand-in: it needs no network and always answers the same
way to the same belief and context, so runs are reproducible. ``OpenAICompatiblePlanner`` asks a
real model through any OpenAI-compatible ``/chat/completions`` endpoint with the paper's prompt
rules; its answer is checked against the closed vocabulary like any other plan (it is text from
a model: parsed, never evaluated).
"""

from __future__ import annotations

import json
import os
import socket
import urllib.error
import urllib.parse
import urllib.request
from typing import Protocol

from .plan import DRAWERS, Branch, PlanError, parse_program

SEARCH_ORDER = DRAWERS


class PlannerError(RuntimeError):
    """The planner could not produce a plan (a model unreachable or answering nonsense)."""


class Planner(Protocol):
    name: str

    def propose(self, task: str, belief: dict, context: dict) -> list[str]:
        """A plan chunk in the text format of :mod:`agents.plan` (3–5 skills, branches at inspections)."""


def drawer_open(executed: list[str], drawer: str) -> bool:
    """Whether the skills done so far leave ``drawer`` open."""
    state = False
    for skill in executed:
        if skill == f"OpenDrawer({drawer}-H)":
            state = True
        elif skill == f"CloseDrawer({drawer}-H)":
            state = False
    return state


class ScriptedPlanner:
    """A deterministic stand-in for the VLM planner: search the drawers in a fixed order
    (TL → TR → BL → BR), branch on every inspection, and finish with the paper's completion
    rules (season, close what was opened, terminate). ``one_skill=True`` is the − plan chunking
    ablation: it proposes only the next skill."""

    name = "scripted"

    def __init__(self, one_skill: bool = False, task_kind: str = "drawers"):
        self.one_skill, self.task_kind = one_skill, task_kind

    def propose(self, task: str, belief: dict, context: dict) -> list[str]:
        executed = list(context.get("executed", []))
        if context.get("current"):
            executed.append(context["current"])           # it will have run when this plan applies
        if self.task_kind == "bag":
            program = self._bag_program(belief, executed)
        else:
            program = self._program(belief, executed)
        if self.one_skill:
            return [self._first(program, belief, self.task_kind)]
        return program

    @staticmethod
    def _bag_program(belief: dict, executed: list[str]) -> list[str]:
        """Open the bag, look in, and take the target out if it is there (the bag task)."""
        seen = belief.get("in(target, bag)", "unknown")
        if "Extract(target)" in executed:
            return ["Done()"]
        if seen == "no":
            return ["Done()"]                             # not in the bag: nothing to take out
        if seen == "yes":
            if belief.get("holding(target)") == "yes":
                return ["Extract(target) -> Done()"]
            # the bag springs shut when the hand leaves it: Pick right after the hand opened it
            # (and looked), else open it again first
            held_open = bool(executed) and executed[-1] in ("OpenBag(bag)", "InspectBag(bag)")
            fetch = ["Pick(target)", "Extract(target)", "Done()"]
            return [" -> ".join(fetch if held_open else ["OpenBag(bag)", *fetch])]
        program = [] if "OpenBag(bag)" in executed else ["OpenBag(bag)"]
        return [" -> ".join(program + ["InspectBag(bag)"]),
                "IF in(target, bag) = yes THEN Pick(target) -> Extract(target) -> Done() ELSE Done()"]

    def _program(self, belief: dict, executed: list[str]) -> list[str]:
        found = next((d for d in DRAWERS if belief.get(f"at(spice, {d})") == "yes"), None)
        if found is not None:
            return self._fetch(found, belief, executed)
        program = [f"CloseDrawer({d}-H)" for d in DRAWERS
                   if drawer_open(executed, d) and belief.get(f"at(spice, {d})") == "no"]
        unknown = [d for d in SEARCH_ORDER if belief.get(f"at(spice, {d})", "unknown") == "unknown"]
        if not unknown:
            return program + ["Done()"]                   # searched everywhere: give up cleanly
        d = unknown[0]
        if not drawer_open(executed, d):
            program.append(f"OpenDrawer({d}-H)")
        program.append(f"InspectDrawer({d})")
        program.append(f"IF at(spice, {d}) = yes THEN Pick(spice) -> Season(food) -> CloseDrawer({d}-H) -> Done() "
                       f"ELSE CloseDrawer({d}-H)")
        return program

    @staticmethod
    def _fetch(drawer: str, belief: dict, executed: list[str]) -> list[str]:
        """The rest of the task once the bottle's drawer is known, from what is already done
        (``holding(spice)`` is the monitor's word on the gripper: after a slip it is "no" again)."""
        opened = {d for d in DRAWERS if drawer_open(executed, d)}
        program = []
        if "Season(food)" not in executed:
            if belief.get("holding(spice)") != "yes":
                if drawer not in opened:
                    program.append(f"OpenDrawer({drawer}-H)")
                    opened.add(drawer)
                program.append("Pick(spice)")
            program.append("Season(food)")
        program += [f"CloseDrawer({d}-H)" for d in DRAWERS if d in opened]
        return [" -> ".join(program + ["Done()"])]

    @staticmethod
    def _first(program: list[str], belief: dict, task_kind: str = "drawers") -> str:
        """The first concrete skill of a program (the branch resolved by the belief, or its
        inspection not yet done)."""
        nodes = parse_program(program, task_kind)
        node = nodes[0]
        while isinstance(node, Branch):
            value = belief.get(node.predicate, "unknown")
            side = node.then if value == node.value else node.otherwise
            node = side[0] if side else nodes[1]
        return str(node)


DRAWERS_PROMPT = """You are a robot task planner.

SCENE OBJECTS:
- spice (pickable; hidden in one of the drawers)
- drawers TL, TR, BL, BR (containers; top-left, top-right, bottom-left, bottom-right), handles TL-H, TR-H, BL-H, BR-H
- food on a plate (surface)

SKILLS (the only ones that exist):
OpenDrawer(<handle>), InspectDrawer(<drawer>), CloseDrawer(<handle>),
Pick(spice), Season(food), PlaceBack(spice), Done()

PREDICATES: at(spice, <drawer>) = yes|no|unknown

ACTION PLAN FORMAT, one string per line:
1. Linear: Skill(arg) -> Skill(arg)
2. Conditional: IF at(spice, <drawer>) = yes THEN <linear> ELSE <linear>

CRITICAL RULES:
1. Always close drawers after use (cleanup).
2. Complete the full task (pick -> season -> close -> Done()).
3. If inspecting, you MUST handle both found/not-found cases.
4. Propose 3 to 5 skills.

OUTPUT JSON: {"action_plan": ["...", "..."], "reasoning": "..."}"""

BAG_PROMPT = """You are a robot task planner.

SCENE OBJECTS:
- target (pickable; maybe inside the bag), bag (a container whose mouth must be opened), a tray spot (surface)

SKILLS (the only ones that exist):
OpenBag(bag), InspectBag(bag), Pick(target), Extract(target), Done()

PREDICATES: in(target, bag) = yes|no|unknown

ACTION PLAN FORMAT, one string per line:
1. Linear: Skill(arg) -> Skill(arg)
2. Conditional: IF in(target, bag) = yes THEN <linear> ELSE <linear>

CRITICAL RULES:
1. Open the bag before looking in or picking.
2. Complete the full task (open -> inspect -> pick -> extract -> Done()).
3. If inspecting, you MUST handle both found/not-found cases.

OUTPUT JSON: {"action_plan": ["...", "..."], "reasoning": "..."}"""

SYSTEM_PROMPTS = {"drawers": DRAWERS_PROMPT, "bag": BAG_PROMPT}


class OpenAICompatiblePlanner:
    """A real VLM/LLM planner over an OpenAI-compatible HTTP endpoint (``base_url`` ending in
    ``/v1``). The API key is read from the environment variable ``api_key_env`` in the planner's
    own process (never sent through the graph or the log)."""

    name = "openai-compatible"

    def __init__(self, base_url: str, model: str, api_key_env: str = "OPENAI_API_KEY", timeout: float = 60.0,
                 task_kind: str = "drawers"):
        if not base_url.startswith(("http://", "https://")):
            raise ValueError(f"planner base_url {base_url!r} must start with http:// or https://")
        self.base_url, self.model, self.api_key_env, self.timeout = base_url.rstrip("/"), model, api_key_env, timeout
        self.task_kind = task_kind

    def check_reachable(self) -> None:
        """Fail now, not a planner latency into the run, when nothing listens at the endpoint."""
        parts = urllib.parse.urlsplit(self.base_url)
        try:
            port = parts.port or (443 if parts.scheme == "https" else 80)
            socket.create_connection((parts.hostname, port), timeout=min(self.timeout, 5.0)).close()
        except (OSError, ValueError) as e:
            raise PlannerError(f"planner endpoint {self.base_url} is not reachable: {e}\n    hint: start the model "
                               "server, or check the URL (openai:http://HOST:PORT/v1#MODEL)") from None

    def propose(self, task: str, belief: dict, context: dict) -> list[str]:
        user = json.dumps({"task": task, "belief": belief, "executed": context.get("executed", []),
                           "current": context.get("current", ""), "failures": context.get("failures", [])})
        body = json.dumps({"model": self.model, "temperature": 0,
                           "messages": [{"role": "system", "content": SYSTEM_PROMPTS[self.task_kind]},
                                        {"role": "user", "content": user}]}).encode()
        headers = {"Content-Type": "application/json"}
        key = os.environ.get(self.api_key_env)
        if key:
            headers["Authorization"] = f"Bearer {key}"
        request = urllib.request.Request(f"{self.base_url}/chat/completions", data=body, headers=headers)
        try:
            with urllib.request.urlopen(request, timeout=self.timeout) as response:
                reply = json.loads(response.read(1 << 20))
            content = reply["choices"][0]["message"]["content"]
        except (urllib.error.URLError, OSError, ValueError, KeyError, IndexError, TypeError, RecursionError) as e:
            raise PlannerError(f"planner endpoint {self.base_url} gave no usable answer: {_brief(e)}") from None
        return parse_answer(content, self.task_kind)


def parse_answer(content: str, task_kind: str = "drawers") -> list[str]:
    """The ``action_plan`` of a model's JSON answer (a fenced code block is accepted), checked."""
    if not isinstance(content, str):
        raise PlannerError("the model's answer is not text")
    text = content.strip()
    if text.startswith("```"):
        text = text.strip("`")
        text = text[text.index("\n") + 1:] if "\n" in text else text
    try:
        plan = json.loads(text)["action_plan"]
        parse_program(plan, task_kind)
    except (ValueError, KeyError, TypeError, RecursionError) as e:  # RecursionError: JSON nested too deep
        raise PlannerError(f"the model's plan is not a program of the vocabulary: {_brief(e)}") from None
    return list(plan)


def _brief(error: BaseException) -> str:
    text = f"{type(error).__name__}: {error}" if isinstance(error, RecursionError) else str(error)
    return text if len(text) <= 300 else text[:300] + "…"


class FixedOrderPlanner:
    """The VLA-only ablation: no planner, no belief; one fixed skill order, tried once."""

    name = "fixed-order"
    ORDERS = {"drawers": ["OpenDrawer(TL-H) -> Pick(spice) -> Season(food) -> CloseDrawer(TL-H) -> Done()"],
              "bag": ["OpenBag(bag) -> Pick(target) -> Extract(target) -> Done()"]}

    def __init__(self, task_kind: str = "drawers"):
        self.order = self.ORDERS[task_kind]

    def propose(self, task: str, belief: dict, context: dict) -> list[str]:
        return list(self.order) if not context.get("executed") and not context.get("failures") else ["Done()"]


def make_planner(spec: str | None, task_kind: str = "drawers") -> Planner:
    """``None``/``"scripted"`` → the stand-in; ``"scripted-one-skill"`` → the ablation;
    ``"openai:<base_url>#<model>"`` → an OpenAI-compatible endpoint; each for ``task_kind``."""
    if task_kind not in ("drawers", "bag"):
        raise ValueError(f"unknown task {task_kind!r}: choose drawers or bag")
    if spec in (None, "", "scripted"):
        return ScriptedPlanner(task_kind=task_kind)
    if spec == "scripted-one-skill":
        return ScriptedPlanner(one_skill=True, task_kind=task_kind)
    if spec == "fixed-order":
        return FixedOrderPlanner(task_kind)
    if spec.startswith("openai:") and "#" in spec:
        url, model = spec[len("openai:"):].rsplit("#", 1)
        return OpenAICompatiblePlanner(url, model, task_kind=task_kind)
    raise ValueError(f"unknown planner {spec!r}: use 'scripted', 'scripted-one-skill' or "
                     "'openai:<base_url>#<model>' (for example openai:http://localhost:8000/v1#qwen2.5-vl)")


__all__ = ["OpenAICompatiblePlanner", "PlanError", "Planner", "PlannerError", "ScriptedPlanner", "make_planner",
           "parse_answer"]
