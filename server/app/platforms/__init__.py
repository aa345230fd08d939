"""The platforms participants come from: ``base`` (the ``Platform`` protocol, every platform's
seam: arrival, completion, withdrawal, review, replica rows; ``BasePlatform``'s defaults), one
module per platform (``lab``; ``mturk``, also boto3's client and the MTurk replica's side;
``prolific_platform``), ``review`` (approving, rejecting and paying bonuses exactly once, behind
one interface for each platform and its local replica), ``prolific`` (Prolific's API client),
``prolific_replica`` (the local Prolific replica's API), ``prolific_sync`` (submission statuses
from Prolific's webhook and a poll) and ``backends`` (the backend ``BAM_REVIEW_BACKEND`` chooses
for a platform). They are found by name in ``server.app.platform_registry``."""
