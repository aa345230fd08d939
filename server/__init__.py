"""BAM Study: the domains, the learners and the study server."""
