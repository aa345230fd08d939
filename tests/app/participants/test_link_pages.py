"""The study page's answers to a bad link read as sentences."""

from __future__ import annotations

from fastapi.testclient import TestClient

PID = "5f8d0d55b54764421b7156c3"


def test_a_prolific_link_that_lacks_an_id_is_answered_with_a_sentence(
    client: TestClient,
) -> None:
    page = client.get(f"/study?PROLIFIC_PID={PID}&STUDY_ID={PID}")
    assert page.status_code == 400, page.text
    assert "This study link is not valid" in page.text
    assert "The Prolific link lacks SESSION_ID." in page.text
