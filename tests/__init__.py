"""The test suite. Its folders mirror the packages (plus papers/ and e2e/) and are packages
themselves, so that each test module has a name of its own (tests.server.sim.test_traffic) and
the helpers in tests/support/ are imported by that name from anywhere."""
