"""An observation term added as docs/extending.md ("Adding an observation term") says: one function, one
registration."""

from runtime.observation.registry import PER_JOINT, register_term


def tracking_error(x):
    """q - a_{t-1} (rad): how far each joint is from the target in force."""
    return x.q - x.last_action


register_term("tracking_error", PER_JOINT, tracking_error)
