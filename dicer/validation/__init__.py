"""Finite-element validation: dicer's meshes solved with CalculiX against closed-form stresses.

Each case makes a label image (``geometry``), takes it through dicer's own stages as
``dicer run --labels`` does (fix, mesh, merge, smooth, export; ``models``), solves the deck
with CalculiX ``ccx`` (``calculix``) and compares the stresses it writes with the analytic
value (``cases``): the Kirsch plate with a hole (2D, quarter and full plate) and the Lamé
thick-walled cylinder (3D). ``python -m dicer.validation`` runs the study of
``docs/validation.md`` and writes its figures and numbers.
"""
