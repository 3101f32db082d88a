"""PPO walking policy for BRUCE (issue #22): the MuJoCo environment, Table II rewards, training and export."""
