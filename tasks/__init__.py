"""What each task is: success, the benchmark referee and its start rule,
the scripted demonstrations. Above systems, below the diagram builders."""
