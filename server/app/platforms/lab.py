"""The lab: participants open the study's address as it is, with no platform ids (a cookie
says who they are), and hand their completion code to the experimenter."""

from __future__ import annotations

from server.app.platforms.base import BasePlatform


class Lab(BasePlatform):
    name = "lab"
    display_name = "the lab"


LAB = Lab()
