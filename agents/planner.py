"""Planners: the VLM that proposes plan chunks, behind one interface (paper Appendix E-d, E-g, I).

``ScriptedPlanner`` is the default stand-in: it needs no network and always answers the same
way to the same belief and context, so runs are reproducible (it has no use for the image).
``OpenAICompatiblePlanner`` asks a real vision-language model through any OpenAI-compatible
``/chat/completions`` endpoint, with the head camera's image, the belief and the paper's prompt
rules (the contract is :mod:`agents.vlm`); its answer is checked against the closed vocabulary
like any other plan (it is text from a model: parsed, never evaluated).
"""

from __future__ import annotations

import http.client
import json
import os
import socket
import time
import urllib.error
import urllib.parse
import urllib.request
from typing import Protocol

import numpy as np

from .plan import DRAWERS, Branch, PlanError, parse_program
from .vlm import EXPECTED, AnswerRefused, chat_messages, check_answer, correction, example, shorten

SEARCH_ORDER = DRAWERS


class PlannerError(RuntimeError):
    """The planner could not produce a plan (a model unreachable or answering nonsense):
    ``problem`` says what happened in one line, ``hint`` what to do about it."""

    def __init__(self, problem: str, hint: str = ""):
        self.problem, self.hint = problem, hint
        super().__init__(problem + (f"\n    hint: {hint}" if hint else ""))


class Planner(Protocol):
    name: str

    def propose(self, task: str, belief: dict, context: dict, image: np.ndarray | None = None) -> list[str]:
        """A plan chunk in the text format of :mod:`agents.plan` (3–5 skills, branches at inspections);
        ``image`` is the head camera's newest frame (RGB), when the graph feeds the planner one."""


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

    def propose(self, task: str, belief: dict, context: dict, image: np.ndarray | None = None) -> list[str]:
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


class OpenAICompatiblePlanner:
    """A real VLM planner over an OpenAI-compatible HTTP endpoint (``base_url`` ending in ``/v1``):
    each request carries the head camera's image and the belief (:mod:`agents.vlm`). An answer
    that is no plan is sent back to the model with what was wrong and asked again, and so is a
    server error (HTTP 5xx, a reply that is no chat completion), up to ``attempts`` requests in
    all; then PlannerError names the endpoint and the last answer. An endpoint that cannot be
    reached, refuses the request (HTTP 4xx) or redirects it fails at once: asking again would not
    help. The API key is read from the environment variable ``api_key_env`` in the planner's own
    process (never sent through the graph or the log) and goes to ``base_url`` only: a redirect is
    not followed."""

    name = "openai-compatible"

    def __init__(self, base_url: str, model: str, api_key_env: str = "OPENAI_API_KEY", timeout: float = 60.0,
                 task_kind: str = "drawers", attempts: int = 3):
        parts = urllib.parse.urlsplit(base_url)
        if parts.username is not None or parts.password is not None:  # shown in every message: say no, quote none
            raise ValueError(f"planner base_url {parts.scheme}://…@{parts.hostname}…: credentials in the URL are "
                             "not sent; give the key in $OPENAI_API_KEY (or api_key_env=)")
        if parts.scheme not in ("http", "https") or not parts.hostname:
            raise ValueError(f"planner base_url {base_url!r} must be an http:// or https:// URL with a host, "
                             "such as http://localhost:8000/v1")
        if type(attempts) is not int or attempts < 1:
            raise ValueError(f"planner attempts={attempts!r} must be an integer >= 1")
        self.base_url, self.model, self.api_key_env, self.timeout = base_url.rstrip("/"), model, api_key_env, timeout
        self.task_kind, self.attempts = task_kind, attempts

    def check_reachable(self) -> None:
        """Fail now, not a planner latency into the run, when nothing listens at the endpoint."""
        parts = urllib.parse.urlsplit(self.base_url)
        try:
            port = parts.port or (443 if parts.scheme == "https" else 80)
            socket.create_connection((parts.hostname, port), timeout=min(self.timeout, 5.0)).close()
        except (OSError, ValueError) as e:
            raise PlannerError(f"planner endpoint {self.base_url} is not reachable: {e}",
                               "start the model server, or check the URL (openai:http://HOST:PORT/v1#MODEL)") from None

    def propose(self, task: str, belief: dict, context: dict, image: np.ndarray | None = None) -> list[str]:
        state = {"task": task, "belief": belief, "executed": context.get("executed", []),
                 "current": context.get("current", ""), "failures": context.get("failures", [])}
        messages = chat_messages(self.task_kind, state, image)
        for _ in range(self.attempts):
            try:
                content = self._complete(messages)
            except _ServerError as e:
                last, server_failed = str(e), True
                continue
            try:
                return check_answer(content, self.task_kind)
            except AnswerRefused as e:
                last, server_failed = str(e), False
                if isinstance(content, str):
                    messages.append({"role": "assistant", "content": content})
                messages.append({"role": "user", "content": correction(e, self.task_kind)})
        limited = "HTTP 429" in last  # it limits the rate: asking less often helps
        hint = (("the model server limits the rate: a longer planner latency asks less often" if limited else
                 "the model server failed, or its reply was no chat completion; its own log says why")
                if server_failed else
                f"the model must answer with only {EXPECTED}, such as {example(self.task_kind)} (docs/retriever0.md)")
        raise PlannerError(f"planner {self.base_url} (model {self.model}) gave no plan in {self.attempts} "
                           f"attempts; the last: {last}", hint)

    def _complete(self, messages: list[dict]):
        """The content of one chat completion; _ServerError for what may go better next time."""
        body = json.dumps({"model": self.model, "temperature": 0, "messages": messages}).encode()
        headers = {"Content-Type": "application/json"}
        key = os.environ.get(self.api_key_env)
        if key:
            headers["Authorization"] = f"Bearer {key}"
        request = urllib.request.Request(f"{self.base_url}/chat/completions", data=body, headers=headers)
        deadline = time.monotonic() + self.timeout
        try:
            with _OPENER.open(request, timeout=self.timeout) as response:
                raw = _read_by(response, deadline)
        except urllib.error.HTTPError as e:
            raise self._refusal(e) from None
        except (urllib.error.URLError, OSError, http.client.HTTPException) as e:
            raise PlannerError(f"planner endpoint {self.base_url} gave no answer: {_brief(e)}",
                               f"is the model server still up? (the planner waits {self.timeout:g} s for an "
                               "answer)") from None
        try:
            return json.loads(raw.decode("utf-8", "replace"))["choices"][0]["message"]["content"]
        except (ValueError, KeyError, IndexError, TypeError, RecursionError) as e:
            text = raw.decode("utf-8", "replace")
            raise _ServerError(f"the endpoint's reply is not a chat completion ({_brief(e)}): {shorten(text)}") \
                from None

    def _refusal(self, error: urllib.error.HTTPError) -> Exception:
        """An HTTP error answer: a server error is tried again, a refusal or a redirect is final."""
        text = error.read(MAX_REPLY_BYTES).decode("utf-8", "replace") if error.fp is not None else ""
        said = f"HTTP {error.code} {error.reason}: {shorten(text)}"
        if error.code >= 500 or error.code == 429:  # overloaded, or limiting the rate: may go better
            return _ServerError(f"the endpoint answered {said}")
        if 300 <= error.code < 400:
            return PlannerError(f"planner endpoint {self.base_url} redirects to {error.headers.get('Location')!r}",
                                "give the URL it redirects to (the API key is sent to the URL given only)")
        hint = {401: f"set the endpoint's API key in ${self.api_key_env}", 403: f"check the key in ${self.api_key_env}",
                404: "the base URL ends where /chat/completions is appended (usually /v1)"}.get(
            error.code, f"check the model name {self.model!r} and the URL")
        return PlannerError(f"planner endpoint {self.base_url} refused the request: {said}", hint)


#: the most of a reply that is read (a chat completion is a few kilobytes)
MAX_REPLY_BYTES = 1 << 20


def _read_by(response, deadline: float) -> bytes:
    """The reply's body, at most MAX_REPLY_BYTES, read whole by ``deadline`` (monotonic): the
    socket's timeout bounds each read only, and a server sending a byte at a time never trips it."""
    parts, size = [], 0
    while size < MAX_REPLY_BYTES:
        if time.monotonic() > deadline:
            raise TimeoutError("the answer did not come whole within the timeout")
        part = response.read1(min(65536, MAX_REPLY_BYTES - size))
        if not part:
            break
        parts.append(part)
        size += len(part)
    return b"".join(parts)


class _ServerError(Exception):
    """The endpoint answered, but not a chat completion (HTTP 5xx, a body of something else)."""


class _NoRedirect(urllib.request.HTTPRedirectHandler):
    """Redirects come back as the HTTP error they are: urllib would follow one with the API key."""

    def redirect_request(self, req, fp, code, msg, headers, newurl):
        return None


_OPENER = urllib.request.build_opener(_NoRedirect)


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

    def propose(self, task: str, belief: dict, context: dict, image: np.ndarray | None = None) -> list[str]:
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


__all__ = ["OpenAICompatiblePlanner", "PlanError", "Planner", "PlannerError", "ScriptedPlanner", "make_planner"]
