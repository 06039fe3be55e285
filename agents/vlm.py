"""The planner's contract with a vision-language model: what one request carries and what its
answer must be (docs/retriever0.md, "The model's contract"). Nothing here opens a connection;
:class:`agents.planner.OpenAICompatiblePlanner` sends these requests.

A request is an OpenAI-compatible chat completion::

    {"model": MODEL, "temperature": 0,
     "messages": [{"role": "system", "content": <the task's prompt: objects, skills, plan format, rules>},
                  {"role": "user", "content": [
                      {"type": "text", "text": <JSON: task, belief, executed, current, failures>},
                      {"type": "image_url", "image_url": {"url": "data:image/png;base64,..."}}]}]}

The answer (``choices[0].message.content``) must be a JSON object whose ``action_plan`` is a
list of 1 to 32 plan lines of the task's vocabulary (:mod:`agents.plan`); a fenced code block or
words around the object are tolerated. Any other answer is refused with :class:`AnswerRefused`,
whose text says what arrived; :func:`correction` is what goes back to the model: that text, what
was expected and an example.
"""

from __future__ import annotations

import base64
import io
import json

import numpy as np

from .plan import MAX_LINES, PlanError, parse_program

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

#: each task's example of a valid answer, shown to the model after a refused one and to the user
EXAMPLES = {
    "drawers": {"action_plan": ["OpenDrawer(TL-H) -> InspectDrawer(TL)",
                                "IF at(spice, TL) = yes THEN Pick(spice) -> Season(food) -> CloseDrawer(TL-H) -> Done() "
                                "ELSE CloseDrawer(TL-H)"],
                "reasoning": "look in the top-left drawer first"},
    "bag": {"action_plan": ["OpenBag(bag) -> InspectBag(bag)",
                            "IF in(target, bag) = yes THEN Pick(target) -> Extract(target) -> Done() ELSE Done()"],
            "reasoning": "open the bag and look in"},
}

EXPECTED = f'a JSON object whose "action_plan" is a list of 1 to {MAX_LINES} plan lines of the vocabulary'

#: how much of a refused answer an error quotes
QUOTED_CHARS = 200


class AnswerRefused(ValueError):
    """A model's answer that is no plan; the text says what arrived (shortened)."""


def shorten(text: str, limit: int = QUOTED_CHARS) -> str:
    """``text`` quoted, cut to ``limit`` characters (an answer can be a page long)."""
    return repr(text) if len(text) <= limit else repr(text[:limit]) + f"… ({len(text)} characters)"


def example(task_kind: str) -> str:
    return json.dumps(EXAMPLES[task_kind])


def correction(refused: AnswerRefused, task_kind: str) -> str:
    """What the model is told after a refused answer: what was wrong, what is expected, an example."""
    return (f"Your answer was refused: {refused}. Answer with only {EXPECTED}, for example: "
            f"{example(task_kind)}")


def check_answer(content, task_kind: str = "drawers") -> list[str]:
    """The ``action_plan`` of a model's answer, checked against ``task_kind``'s vocabulary, or
    AnswerRefused saying what arrived. The answer is text from a model: parsed, never evaluated."""
    if not isinstance(content, str):
        raise AnswerRefused(f"the answer is not text but {type(content).__name__}")
    answer = _json_object(content)
    if not isinstance(answer, dict) or "action_plan" not in answer:
        raise AnswerRefused(f'the answer has no "action_plan": {shorten(content.strip())}')
    plan = answer["action_plan"]
    try:
        parse_program(plan, task_kind)
    except PlanError as e:
        raise AnswerRefused(f'its "action_plan" is not a program of the {task_kind} vocabulary ({e}): '
                            f"{shorten(json.dumps(plan))}") from None
    return list(plan)


def _json_object(content: str):
    """The JSON value of an answer: the whole text, a fenced block's, or what lies between its
    first ``{`` and its last ``}`` (models put words around it)."""
    text = content.strip()
    if text.startswith("```"):
        text = text.strip("`")
        text = text[text.index("\n") + 1:] if "\n" in text else text
    try:
        return json.loads(text)
    except (ValueError, RecursionError) as first:   # RecursionError: JSON nested too deep
        start, end = text.find("{"), text.rfind("}")
        if 0 <= start < end:
            try:
                return json.loads(text[start:end + 1])
            except (ValueError, RecursionError):
                pass
        reason = f"{type(first).__name__}: {first}" if isinstance(first, RecursionError) else str(first)
        raise AnswerRefused(f"the answer is not JSON ({reason}): {shorten(content.strip())}") from None


def png_data_url(rgb: np.ndarray) -> str:
    """An RGB image (uint8, H×W×3) as a ``data:image/png;base64,`` URL. Pillow comes with
    matplotlib, a dependency of the project (it draws the demo's pictures)."""
    from PIL import Image

    if not (isinstance(rgb, np.ndarray) and rgb.dtype == np.uint8 and rgb.ndim == 3 and rgb.shape[2] == 3):
        raise ValueError(f"the planner's image must be uint8 H×W×3 RGB, got "
                         f"{getattr(rgb, 'dtype', type(rgb).__name__)} {getattr(rgb, 'shape', '')}")
    buffer = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(rgb)).save(buffer, format="PNG")
    return "data:image/png;base64," + base64.b64encode(buffer.getvalue()).decode("ascii")


def chat_messages(task_kind: str, state: dict, image: np.ndarray | None) -> list[dict]:
    """The first messages of a request: the task's system prompt, then the state as JSON text
    with the head camera's image (text alone when no frame has arrived yet)."""
    text = json.dumps(state)
    user = text if image is None else [{"type": "text", "text": text},
                                       {"type": "image_url", "image_url": {"url": png_data_url(image)}}]
    return [{"role": "system", "content": SYSTEM_PROMPTS[task_kind]}, {"role": "user", "content": user}]


__all__ = ["AnswerRefused", "EXAMPLES", "EXPECTED", "SYSTEM_PROMPTS", "chat_messages", "check_answer", "correction",
           "example", "png_data_url", "shorten"]
