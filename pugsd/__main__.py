# SPDX-License-Identifier: Apache-2.0
from pugsd.cli import main

raise SystemExit(main())
