"""The participant's way through a study, below the web layer.

``tokens`` (statuses and the participant's token), ``arrival`` (who may start, from each
platform), ``transaction`` (``perform``: every request that changes something, in one write
transaction with its event), ``assignment`` (consent, the balanced domains, the order of
sessions), ``teaching`` (moves, modes, feedback and episodes in a learning session),
``completion`` (tutorial steps, questionnaire, completion code) and ``views`` (what the page is
shown).
"""
