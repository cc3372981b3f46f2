"""Live hardware mode: ABB EGM poses over UDP, profiles over TCP or scanCONTROL, crash-safe
recording, clock alignment and the continuous monitoring run (:mod:`dm2.live.runner`)."""
