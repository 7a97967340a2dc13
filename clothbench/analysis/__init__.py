"""Accuracy and stability: how wrong each backend is, what a larger dt costs, and where it breaks.

- convergence.py: implementation and discretisation error against cost, per backend, mode and
  solver, each model against its own converged float64 reference, and the convergence order;
- artefacts.py: what PBD changes against the mass-spring model (softness, numerical damping);
- lattice.py: the linearised stability limit of the flat lattice and the Gershgorin bound;
- stability.py: the largest stable dt, measured by bisection, beside those limits.

docs/accuracy.md has the numbers and the reasoning. The variants come from
harness.plan.plan_variants, as every other command's do; the plots are in
reports/accuracy_plots.py.
"""
