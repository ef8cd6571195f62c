"""The wire between a gateway and the central site (issue 17): what a gateway uploads, pure models only."""
