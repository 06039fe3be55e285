"""The learning loop on Retriever-0's Pick skill: collect episodes of the scripted skill (logs),
export them as a dataset (``retriever log export``), train a small policy on the export into a
checkpoint a :class:`retriever.learn.TorchPolicy` runs, and evaluate it against the scripted one.

    python -m agents.learn all --episodes N --train-seeds A:B --eval-seeds C:D --minutes M -o DIR

(or its steps: ``collect``, ``export``, ``train``, ``evaluate``). The policy is the one of the
``pick_policy`` flow (:class:`agents.flows.SkillActor` scripted, :class:`agents.flows.LearnedSkill`
learned); its step records hold exactly what it consumed and the chunk it sent (docs/learning.md).
"""
