"""Research diagnostics: experiments that explain a result (imitation and DAgger probes of the
observation, the safety shield behind a trained policy, the crowd-timing interventions), as
opposed to the speed claims in `benchmarks/`."""
