"""Assemblies: the model an assembly file describes (model), its YAML reading and atomic writing (fileio,
yamlcheck), mates, CAD meshes (mesh) and a printable summary."""
