"""The FE engine: material law, assembly, skin membrane, rigid plates, Newton solver and the
reference paper's two simulation steps (`fem.engine.simulation`). Imports only
`fem.contract`."""
