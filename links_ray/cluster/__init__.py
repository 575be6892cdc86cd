"""The Ray roles that build the dataset: joining a cluster, generation actors, and curation on
Ray Data."""
