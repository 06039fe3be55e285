"""Plan chunks: the paper's text format parsed against the closed vocabulary, and the splice rule."""

import pytest

from agents.plan import Branch, PlanError, Skill, format_program, parse_program, remaining_skills, splice

S = Skill


def test_a_chunk_in_the_papers_format_parses_and_prints_back():
    program = ["OpenDrawer(TL-H) -> InspectDrawer(TL)",
               "IF at(spice, TL) = yes THEN Pick(spice) -> Season(food) -> CloseDrawer(TL-H) -> Done() "
               "ELSE CloseDrawer(TL-H)"]
    nodes = parse_program(program)
    assert nodes == [S("OpenDrawer", "TL-H"), S("InspectDrawer", "TL"),
                     Branch("at(spice, TL)", "yes", (S("Pick", "spice"), S("Season", "food"),
                                                     S("CloseDrawer", "TL-H"), S("Done", "")),
                            (S("CloseDrawer", "TL-H"),))]
    assert format_program(nodes) == program
    assert parse_program(["IF at( spice ,TR )=no THEN CloseDrawer(TR-H)"]) == [
        Branch("at(spice, TR)", "no", (S("CloseDrawer", "TR-H"),), ())]


@pytest.mark.parametrize("program, message", [
    (["Teleport(TL)"], "unknown skill 'Teleport'"),
    (["OpenDrawer(XX-H)"], "OpenDrawer takes one of"),
    (["Pick(salt)"], "Pick takes one of 'spice'"),
    (["OpenDrawer(TL-H) -> "], "is not a skill call"),
    (["IF holding(robot, spice) = yes THEN Season(food)"], "is not a predicate"),
    (["IF at(spice, XX) = yes THEN Season(food)"], "at relates one of"),
    (["__import__('os').system('true')"], "is not a skill call"),
    ([], "a plan is a list of 1 to 32 lines, got 0 lines"),
    ("OpenDrawer(TL-H)", "a plan is a list of 1 to 32 lines, got str"),
    ([42], "must be a string"),
    (["Done()"] * 33, "a plan is a list of 1 to 32 lines, got 33 lines"),
    (["Done() -> " * 100 + "Done()"], "at most 400 characters"),
])
def test_a_plan_outside_the_vocabulary_is_refused_naming_the_line(program, message):
    with pytest.raises(PlanError, match=message.replace("(", r"\(").replace(")", r"\)")):
        parse_program(program)


A, B, C, D, E = *(S("OpenDrawer", h) for h in ("TL-H", "TR-H", "BL-H", "BR-H")), S("Pick", "spice")


@pytest.mark.parametrize("proposal, anchor, expected", [
    # the paper's example: ran C, proposal A, B, C, D, E -> D, E
    ([A, B, C, D, E], C, [D, E]),
    # the anchor not in the proposal: all of it comes next
    ([D, E], C, [D, E]),
    ([C, D], None, [C, D]),
    # a branch stops the search for the anchor
    ([A, Branch("at(spice, TL)", "yes", (C,), ()), C, D], C, [A, Branch("at(spice, TL)", "yes", (C,), ()), C, D]),
])
def test_splice(proposal, anchor, expected):
    assert splice(proposal, anchor) == expected


def test_remaining_skills_counts_what_is_certain_to_run():
    branch = Branch("at(spice, TL)", "yes", (A, B, C), (D,))
    assert remaining_skills([A, B]) == 2
    assert remaining_skills([A, branch]) == 2
    assert remaining_skills([S("Done", ""), A]) == 1
