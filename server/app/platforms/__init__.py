"""The recruitment platforms' side: review of submitted work and bonuses (``review``), the
MTurk backends (``mturk``), Prolific's API client (``prolific``) and its local replica
(``prolific_replica``)."""
