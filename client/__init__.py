"""The agent: dataset readers, front-end, second-stage fusion, server link."""
