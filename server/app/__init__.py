"""The study server: the participant flow and teaching API, SQL persistence, learner updates
off the request path, exports and the experimenter's commands."""
