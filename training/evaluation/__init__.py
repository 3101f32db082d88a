"""`bruce-eval`: held-out accuracy and cost of the dynamics models (`dynamics`) and the sim-to-real transfer
rehearsal (`transfer`). Nothing here imports torch at package import: `bruce-eval transfer` runs on the base install."""
