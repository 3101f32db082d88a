"""Training side: the dataset format and its collection, the learned dynamics models (`training.dynamics`), their
evaluation and the transfer rehearsal (`training.evaluation`), and the walking policy's distillation."""
