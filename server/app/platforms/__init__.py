"""The crowd platforms: ``review`` (approving, rejecting and paying bonuses exactly once, behind
one interface for each platform and its local replica), ``mturk`` (boto3's client and the MTurk
replica's side), ``prolific`` (Prolific's API client), ``prolific_replica`` (the local Prolific
replica's API), ``prolific_sync`` (submission statuses from Prolific's webhook and a poll) and
``backends`` (the backend ``BAM_REVIEW_BACKEND`` chooses for a platform)."""
