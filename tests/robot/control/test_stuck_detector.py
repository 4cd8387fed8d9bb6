def test_a_stuck_streak_escalates_reverse_unwind_creep() -> None:
    """Known answer: after a clockwise turn that did not turn the robot (wedged in a door),
    the recoveries are reverse, a counter-clockwise turn in place, a slow counter-clockwise
    forward arc, then reverse again; after a counter-clockwise turn, the other way."""
    from robot.control.stuck_detector import StuckConfig, recovery_command

    cfg = StuckConfig()
    cw = [recovery_command(k, -1.2, 0.3, cfg) for k in range(4)]
    assert cw == [
        (-0.3, 0.0),
        (0.0, cfg.recovery_turn_rad_s),
        (cfg.recovery_creep_m_s, cfg.recovery_turn_rad_s),
        (-0.3, 0.0),
    ]
    ccw = [recovery_command(k, 0.8, 0.3, cfg) for k in range(3)]
    assert ccw[1] == (0.0, -cfg.recovery_turn_rad_s) and ccw[2][1] < 0 < ccw[2][0]
