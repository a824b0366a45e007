from kinreg_cli.main import main

main()
