"""The learning loop on Retriever-0's Pick skill: collect episodes of the scripted skill (logs),
read them into a dataset, train a small policy, and evaluate a policy against the scripted one.

    python -m agents.learn collect  --episodes N --seeds A:B -o DIR
    python -m agents.learn train    DIR -o policy.pt [--minutes M]
    python -m agents.learn evaluate --seeds A:B [--skill-policy policy.pt]

The policy is the one of the ``pick_policy`` flow (:class:`agents.flows.SkillActor`); its step
records hold exactly what it consumed and the chunk it sent (docs/learning-loop.md).
"""
