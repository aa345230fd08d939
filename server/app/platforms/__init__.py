"""The crowd platforms: ``review`` (approving, rejecting and paying bonuses, behind one
interface for each platform and its local replica)."""
