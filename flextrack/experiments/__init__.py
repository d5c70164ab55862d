"""The paper's experiments rerun: `flextrack experiment table2|ablation|timing|euroc --out DIR`."""
