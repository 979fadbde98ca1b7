"""Starting and watching pipelines: node kinds and trackers found where they are declared,
pipeline files, ``artrack run`` jobs and ``artrack up`` daemons, the supervisor, the router,
access rules and status."""
