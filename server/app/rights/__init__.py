"""Participants' rights: erasure on request with an audit trail (``erasure``) and platform ids
that expire (``scrub``)."""
