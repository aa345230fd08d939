"""The fixtures the study server's tests share (databases, the app, an update pool), from
tests/support/server.py, for every test folder: tests/app mirrors server/app room by room, and
tests/commands, tests/browser and tests/analysis drive the same server."""

pytest_plugins = ["tests.support.server"]
