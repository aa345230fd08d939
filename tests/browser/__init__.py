"""Browser tests: the participant's page, the dashboard and the MTurk replica in headless Chromium."""
