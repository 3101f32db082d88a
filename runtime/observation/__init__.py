"""The walking policy's observation, one definition for the runtime (one robot) and training (a batch of them).

`registry`: the observation terms by name, each one width and one batched function; `builtin_terms` registers ours
(the paper's Table I and legged_gym's); `inputs`: what a term function reads; `spec_terms`: a spec's terms with its
offsets, clips, scales, history and joint order applied, for any batch; `builder`: the gait clock and heading
reference that turn measurements into a term's inputs, then the spec's observation. Adding a term: docs/extending.md
("Adding an observation term").

Nothing is imported here: `runtime.control.policy_spec` reads the registry while `builder` reads the spec, and a
package that imported both would import them in a circle.
"""
